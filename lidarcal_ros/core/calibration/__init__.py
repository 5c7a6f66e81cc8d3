"""The calibration procedure: strip pairs, TIN matching, iteration, result."""
