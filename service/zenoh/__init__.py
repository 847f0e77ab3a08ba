"""The Zenoh transport: bridge, ROS 2 codecs, map queryables, config."""
