"""rgbd-seq / rgbd-rig read and write, EXR, importers of other renderers' layouts, LLFF captures as shipped."""
