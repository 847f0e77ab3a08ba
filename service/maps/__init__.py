"""Route maps: the file format, building from rounds, uploaded round archives."""
