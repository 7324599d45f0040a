"""Evaluation: retrieval recall and the gallery index (segmentation and image scores live beside them)."""
from geoloc.eval.search_index import GalleryIndex
from geoloc.eval.image import image_scores
from geoloc.eval.recall import recall_at_k
from geoloc.eval.segmentation import segmentation_scores

__all__ = ["GalleryIndex", "image_scores", "recall_at_k", "segmentation_scores"]
