"""Coding and retrieval for dynamic-scene place recognition (MMDIP): SPM, ORB bag of words, fused similarity."""

from geoloc.vpr.bow import ORBExtractor, Vocabulary
from geoloc.vpr.fusion import Gallery, fused_descriptors, fused_similarity, l2_normalize
from geoloc.vpr.spm import spm_dim, spm_encode

__all__ = [
    "Gallery", "ORBExtractor", "Vocabulary", "fused_descriptors", "fused_similarity", "l2_normalize",
    "spm_dim", "spm_encode",
]
