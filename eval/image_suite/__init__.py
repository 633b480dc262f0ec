"""Image-suite code shared by the eval/ entry scripts: FID/sFID, DiT sampling for evaluation and the
diffusers cache baselines."""
