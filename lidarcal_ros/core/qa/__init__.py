"""Quality measures of a mission: accuracy, swath differences, quality level, land cover."""
