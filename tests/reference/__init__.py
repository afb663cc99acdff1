"""The numpy references of compiled kernels (not part of the package)."""
