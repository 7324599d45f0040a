"""Coding and retrieval for dynamic-scene place recognition (MMDIP): SPM, ORB bag of words, fused similarity."""

from geoloc.vpr.spm import spm_encode

__all__ = ["spm_encode"]
