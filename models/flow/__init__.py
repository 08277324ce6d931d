"""The 3D flow network of DeCOMPnet (thesis Sec. 6.3.3), its losses and its training."""
