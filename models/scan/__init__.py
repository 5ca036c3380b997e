"""The paper's scan: the Archimedean spiral and the simulated spiral scan of an eye."""
