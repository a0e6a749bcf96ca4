"""The optional parts of the install and a clear error when one is missing.

``pip install mmctl`` gives the daemon and its transports.  The extras add the rest:
``[telemetry]`` (rerun, its dataframe reader), ``[study]`` (the figures), ``[bench]``
(the OSQP comparison); ``[test]`` pulls in all of them.
"""

from __future__ import annotations

import importlib.util

from mmctl.errors import MmctlError

#: extra -> the modules it provides
EXTRAS = {"telemetry": ("rerun", "pyarrow", "datafusion"), "study": ("matplotlib",),
          "bench": ("osqp",), "ros2": ("cyclonedds",)}


def require(extra: str, what: str) -> None:
    """Raise :class:`MmctlError` naming the extra when one of its modules is missing.

    what: the feature that needs it, for the message ("telemetry (--viewer)").
    """
    missing = [m for m in EXTRAS[extra] if importlib.util.find_spec(m) is None]
    if missing:
        raise MmctlError(f"{what} needs the '{extra}' extra (missing: {', '.join(missing)}): "
                         f"pip install 'mmctl[{extra}]'")
