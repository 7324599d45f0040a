"""`geoloc bench`: many checkpoints on many test sets under the FoV / heading protocols, in one table beside the
published figures (docs/bench.md)."""
