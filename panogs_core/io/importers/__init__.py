"""Dataset and capture layouts converted into scene bundles: ScanNet, Replica, 7-Scenes, nerfstudio, Record3D,
TUM RGB-D."""
