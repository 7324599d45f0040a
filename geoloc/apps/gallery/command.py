"""`geoloc gallery merge SHARD_DIR... out=DIR [overwrite=true]`: one gallery from the shards that independent jobs
encoded (geoloc/gallery/shards.py; docs/distributed.md)."""

from __future__ import annotations

import sys
from dataclasses import dataclass

from omegaconf import MISSING

from geoloc.config import ConfigError

USAGE = """usage: geoloc gallery merge SHARD_DIR [SHARD_DIR ...] out=DIR [overwrite=true]

  SHARD_DIR   a folder written by one shard job: python evaluate.py ckpt=CKPT gallery.num_shards=S
              gallery.shard_index=i gallery.save=SHARD_DIR [gallery.codebook=CODEBOOK_DIR] (shell globs work:
              shards/*); all S shards, each once, of one checkpoint, split and codebook
  out         the gallery folder to write (whole or not at all): evaluate.py gallery.load=DIR, localize.py and
              geoloc serve open it
  overwrite   replace a gallery already in out"""


@dataclass
class MergeKeys:  # geoloc/conf/gallery_merge.yaml extends this node (schema/gallery_merge)
    out: str = MISSING
    overwrite: bool = False


def main(args: list[str]) -> int:
    from geoloc.gallery import merge_shards
    from geoloc.launch.hydra_hooks import compose_checked

    if not args or args[0] != "merge":
        raise ConfigError(f"unknown gallery action {args[0] if args else '(none)'!r}: geoloc gallery merge ...")
    folders = [a for a in args[1:] if "=" not in a]
    keys = compose_checked("gallery_merge", MergeKeys, [a for a in args[1:] if "=" in a], "gallery merge")
    info, calibration = merge_shards(folders, keys.out, overwrite=keys.overwrite)
    print(f"{keys.out}: {info['num_references']:,} references ({info['kind']}) from {len(folders)} shards")
    if not calibration["calibrated"]:
        print(f"geoloc gallery: {keys.out} is uncalibrated for the top-1 tile: {calibration['why']}", file=sys.stderr)
    return 0
