"""Horizontal and 3D displacement between two epochs.

- :mod:`tiledsm.displace.correlate`: sub-pixel frequency-domain correlation
  of image windows (pure numpy);
- :mod:`tiledsm.displace.field`: the tiled displacement field of two
  orthoimages (one ``map_overlap``).
"""

from tiledsm.displace.correlate import CorrelationParams, correlate_windows
from tiledsm.displace.field import check_same_grid, correlate_orthos

__all__ = ["CorrelationParams", "correlate_windows", "correlate_orthos", "check_same_grid"]
