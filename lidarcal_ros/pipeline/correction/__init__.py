"""Correction of clouds and bags, batch and live (the corrector node's work)."""
