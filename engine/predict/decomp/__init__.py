"""DeCOMPnet in the engine (thesis Ch. 6): MPIs, the motion gate, the 3D flow network, splatting, infilling."""
