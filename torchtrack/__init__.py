"""torchtrack: classical tracking-by-detection in PyTorch.

Box convention (used everywhere unless a name says otherwise): ``x, y, w, h`` in pixels,
``(x, y)`` the top-left corner, 0-based, in the frame's own pixel grid. See
:mod:`torchtrack.boxes` for conversions.
"""

__version__ = "0.1.0"
