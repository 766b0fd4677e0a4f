"""Kernels of the baseline methods (SMT, RTPT, CMax-GAE), apart from the CMax math they build on."""
