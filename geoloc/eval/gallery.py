"""Deprecated name of geoloc.eval.search_index (the search index, GalleryIndex), kept for one release: the saved
gallery is geoloc.gallery, and the two names no longer collide."""

import warnings

from geoloc.eval.search_index import *  # noqa: F401,F403
from geoloc.eval.index_kinds import IndexParams, KINDS, PQ_KINDS, import_faiss  # noqa: F401
from geoloc.eval.search_index import GalleryIndex, faiss_file  # noqa: F401

warnings.warn("geoloc.eval.gallery is geoloc.eval.search_index now; the old name goes in the next release",
              DeprecationWarning, stacklevel=2)
