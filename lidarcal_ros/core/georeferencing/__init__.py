"""Point positioning: the bias model, the rigorous model, the local trajectory."""
