"""Workflows built on the CMax-SLAM core: grayscale mapping, star tracking, super-resolution."""
