"""The HTML calibration report: its content, figures, sections and page."""
