"""Components defined outside the geoloc package, one file and one yaml each (docs/extending.md)."""
