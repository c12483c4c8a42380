"""Sensorless position control: the identified model inverted sample by sample (ROS-free)."""
