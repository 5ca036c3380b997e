"""Calibration of the iiOCT sensor pose: the plate calibration and the paper's study of how
a pose error changes the fitted eye size."""
