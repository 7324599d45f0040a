"""Evaluation: retrieval recall and the gallery index (segmentation and image scores live beside them)."""
from geoloc.eval.gallery import GalleryIndex
from geoloc.eval.recall import recall_at_k

__all__ = ["GalleryIndex", "recall_at_k"]
