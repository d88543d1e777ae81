"""Event processing and the 4D supervision pipeline that reads takes."""
