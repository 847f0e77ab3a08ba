"""Pixels to features: imaging, RootSIFT features, matcher, place index, two-view geometry."""
