"""The method, free of Hydra and run folders: typed options and their rules, checks, build
(scene + options -> discrete problem), reconstruct (levels, weight selection, camera
refinement and capture calibration, photometry, debias, absorption, joint frames)."""
