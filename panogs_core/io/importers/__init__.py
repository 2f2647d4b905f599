"""Dataset layouts converted into scene bundles: ScanNet (SensReader export) and Replica (NICE-SLAM layout)."""
