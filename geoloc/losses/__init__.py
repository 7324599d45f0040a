"""Losses: the cross-view soft-margin triplet and its global hard-negative queue."""
from geoloc.losses.gms_queue import GMSQueue
from geoloc.losses.triplet import soft_margin_triplet

__all__ = ["GMSQueue", "soft_margin_triplet"]
