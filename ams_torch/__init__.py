"""ams_torch: dense hair simulation with the Augmented Mass-Spring model in PyTorch."""
__version__ = "0.1.0"
