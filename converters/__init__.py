"""Readers that turn recordings (TUM RGB-D, ScanNet, ROS bags, synthetic) into frame stores."""
