"""The deployable gallery: a saved gallery folder (the index, each reference's place, the queries' split), the
shards a large one is built from and their merge, its build settings (index_settings.py: evaluate.py's gallery.*
keys), the confidence fitted on held-out queries, and the answer type an app returns. It knows no method: the
cross-view task writes it (tasks/crossview/gallery_build.py), the apps read it."""

from geoloc.gallery.answer import LocalizationResult
from geoloc.gallery.append import append_galleries
from geoloc.gallery.folder import SavedGallery, open_gallery
from geoloc.gallery.places import POSITION_KEYS, Places, read_places
from geoloc.gallery.shards import merge_shards

__all__ = ["LocalizationResult", "POSITION_KEYS", "Places", "SavedGallery", "append_galleries", "merge_shards",
           "open_gallery", "read_places"]
