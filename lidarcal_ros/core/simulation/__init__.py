"""Simulated missions with known biases: terrain, flight, scanner, truth."""
