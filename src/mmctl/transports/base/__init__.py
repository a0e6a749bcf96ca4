"""The omnidirectional base: the :class:`Base` protocol and its transports.

``open_base(cfg)`` builds the transport ``base.transport`` names (``canopen`` or
``serial``), unconnected; use it as a context manager (``with open_base(cfg) as base:``
connects and, on exit, stops, disables and closes).
"""

from __future__ import annotations

from mmctl.transports.base.factory import TRANSPORTS, open_base
from mmctl.transports.base.protocol import WHEEL_NAMES, Base, DriveStatus

__all__ = ["TRANSPORTS", "WHEEL_NAMES", "Base", "DriveStatus", "open_base"]
