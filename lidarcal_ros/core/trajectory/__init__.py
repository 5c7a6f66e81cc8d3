"""The trajectory: live buffer, per-strip errors, rebuilding it from returns."""
