"""The Viser web dashboard service: watch the bag, the plan and the arms live, and run the rig.

`Dashboard` (server.py) owns a viser server with the scene (scene.py) and the panel (panel.py);
its `on_*` methods take the rig's messages from any thread. The panel acts through a `RunLink`
(runlink.py); `node.py` connects both to Zenoh. `bagit dashboard` runs it.
"""

from bagit.dashboard.runlink import RunLink
from bagit.dashboard.server import Dashboard, DashboardConfig

__all__ = ["Dashboard", "DashboardConfig", "RunLink"]
