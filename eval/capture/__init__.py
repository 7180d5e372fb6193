"""How a synthetic plant's cloud is made and a cloud's flowers found without truth: the
simulated scan and photogrammetry, the simulated depth camera fused, the detection through
the stage cache, and a reconstruction measured against the truth mesh."""
