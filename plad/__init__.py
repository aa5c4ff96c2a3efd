"""PLAD: infer shape programs from shapes (CVPR 2022, Jones, Walke, Ritchie)."""

__version__ = "0.1.0"
