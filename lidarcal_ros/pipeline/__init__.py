"""The procedures both front ends drive, so batch and live runs cannot drift apart."""
