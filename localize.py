"""Localize street images against a saved gallery: python localize.py ckpt=.../best.pt gallery=DIR image=FILE_OR_DIR
[topk=5] [fov=360] [heading=null] [out=DIR]. Prints one JSON line per image and writes them to out/localize.jsonl,
with a picture per image (geoloc/apps/localize/)."""

from geoloc.entry_points import localize as main  # composes geoloc/conf/localize.yaml with the arguments

if __name__ == "__main__":
    main()
