"""Files in and out: rosbag2 / MCAP bags, the Drive CDR codec, message definitions, GeoJSON."""
