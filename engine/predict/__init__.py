"""Frame predictors: the interface, the registry (``decomp[k=v]`` parsed here), the classic methods, DeCOMPnet."""
