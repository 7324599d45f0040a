"""Export a cross-view checkpoint's encoders: python export.py ckpt=outputs/.../best.pt [format=onnx] [out=DIR]
[opset=N] [overwrite=true]. Writes query.onnx, reference.onnx and encoders.json (what each file expects)."""

from geoloc.entry_points import export as main  # composes geoloc/conf/export.yaml with the arguments

if __name__ == "__main__":
    main()
