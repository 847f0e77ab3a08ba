"""swarmloc service: route maps, image similarity, the DPSO/PF localizers and the transports."""

__version__ = "0.1.0"
