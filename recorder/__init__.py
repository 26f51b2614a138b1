"""recorder stage."""
