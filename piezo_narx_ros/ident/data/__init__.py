"""Records for identification: loaders, checks, units, coverage, saturation, resampling."""
