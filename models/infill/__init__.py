"""The disocclusion infilling network (thesis Sec. 6.3.4) and its training."""
