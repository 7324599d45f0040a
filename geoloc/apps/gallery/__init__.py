"""`geoloc gallery`: work on saved galleries (command.py)."""
