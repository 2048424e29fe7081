"""detect: Frames -> Detections (ONNX)."""
