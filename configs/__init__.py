"""Package data of fftune (fftune.configs): od.yaml, the generated EDS, example configurations."""
