"""Deployment: a trained checkpoint's encoders in formats that run without geoloc (export.py, format=onnx)."""
