"""How a local Ray copes with a busy host: the settings its processes read from the environment.

A Ray's GCS asks each raylet for a health check every 3 s and, by Ray's defaults, takes the node for dead
after 5 checks left unanswered for 10 s each. A raylet starved of CPU for about a minute (a ``nice`` +15
run beside busy processes, a paused machine) is then terminated, and with it every run of that Ray: the
driver fails with ``LocalRayletDiedError``. :data:`STALL_TOLERANCE` gives a check a minute (a raylet that has
died still refuses the check at once, so it is found as fast as before) and lets Ray's processes wait 5 minutes
for a starved GCS. :func:`~atdrone.service.driver.init_ray` sets them for a local start unless already set; a
``ray start`` of one's own reads them from its environment too.
"""

from __future__ import annotations

STALL_TOLERANCE = {"RAY_health_check_timeout_ms": "60000", "RAY_gcs_rpc_server_reconnect_timeout_s": "300"}
