"""`geoloc gallery merge SHARD_DIR... out=DIR` (one gallery from the shards that independent jobs encoded:
geoloc/gallery/shards.py) and `geoloc gallery append GALLERY_DIR PART_DIR... out=DIR` (new references added to a
gallery without a rebuild: geoloc/gallery/append.py); docs/distributed.md."""

from __future__ import annotations

import sys
from dataclasses import dataclass

from omegaconf import MISSING

from geoloc.config import ConfigError

USAGE = """usage: geoloc gallery merge SHARD_DIR [SHARD_DIR ...] out=DIR [overwrite=true]
       geoloc gallery append GALLERY_DIR PART_DIR [PART_DIR ...] out=DIR [overwrite=true]

  SHARD_DIR   a folder written by one shard job: python evaluate.py ckpt=CKPT gallery.num_shards=S
              gallery.shard_index=i gallery.save=SHARD_DIR [gallery.codebook=CODEBOOK_DIR] (shell globs work:
              shards/*); all S shards, each once, of one checkpoint, split and codebook
  GALLERY_DIR a gallery filled from a codebook (merged from shards, or appended to before)
  PART_DIR    new references: shard folders that the same checkpoint encoded from another split, filled from the
              gallery's codebook (gallery.codebook=CODEBOOK_DIR), or a gallery appended the same way
  out         the gallery folder to write (whole or not at all): evaluate.py gallery.load=DIR, localize.py and
              geoloc serve open it; out=GALLERY_DIR overwrite=true appends in place
  overwrite   replace a gallery already in out"""


@dataclass
class FolderKeys:  # geoloc/conf/gallery_folders.yaml extends this node (schema/gallery_folders)
    out: str = MISSING
    overwrite: bool = False


def main(args: list[str]) -> int:
    from geoloc.gallery import append_galleries, merge_shards
    from geoloc.launch.hydra_hooks import compose_checked

    action = args[0] if args else None
    if action not in ("merge", "append"):
        raise ConfigError(f"unknown gallery action {action or '(none)'!r}: geoloc gallery merge|append ...")
    folders = [a for a in args[1:] if "=" not in a]
    keys = compose_checked("gallery_folders", FolderKeys, [a for a in args[1:] if "=" in a], f"gallery {action}")
    if action == "merge":
        info, calibration = merge_shards(folders, keys.out, overwrite=keys.overwrite)
        print(f"{keys.out}: {info['num_references']:,} references ({info['kind']}) from {len(folders)} shards")
    else:
        if not folders:
            raise ConfigError("give the gallery and the parts: geoloc gallery append GALLERY_DIR PART_DIR... out=DIR")
        info, calibration = append_galleries(folders[0], folders[1:], keys.out, overwrite=keys.overwrite)
        print(f"{keys.out}: {info['num_references']:,} references ({info['kind']}), {len(folders) - 1} part(s) "
              f"appended to {folders[0]}")
    if not calibration["calibrated"]:
        print(f"geoloc gallery: {keys.out} is uncalibrated for the top-1 tile: {calibration['why']}", file=sys.stderr)
    return 0
