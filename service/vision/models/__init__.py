"""Model files shipped with the service (XFeat as ONNX): see NOTICE."""
