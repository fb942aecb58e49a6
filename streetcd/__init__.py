"""streetcd: 3D change detection at street level (Qin & Gruen 2014) as a nightly workflow."""

__version__ = "0.1.0"
