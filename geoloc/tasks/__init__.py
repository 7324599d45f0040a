"""Methods plugged into the engine: `crossview` (MSAE cross-view geo-localization) and `mmdip` (dynamic scenes)."""
