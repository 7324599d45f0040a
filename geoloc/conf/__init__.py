"""geoloc's Hydra configs (a package, so Hydra finds them inside an installed wheel: pkg://geoloc.conf)."""
