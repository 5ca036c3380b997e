"""Run logs: MCAP writing (Foxglove schemas), the filter-step codec, and replay."""
