"""Task objects: reward terms, success and episode statistics."""
