"""dronecap.gap9: the analytical GAP9 cost model of a Tiny-DroNeRF configuration.

Memory per level of the GAP9 hierarchy, operations per step, latency, energy, the federated
link, and whether it fits (:func:`cost_report`); the platform lives in ``gap9.yaml``; the
paper's published figures and the calibration are in :mod:`dronecap.gap9.paper`, the budget
search in :mod:`dronecap.gap9.search`. The NeRF core never imports this package.
"""

from dronecap.gap9.model import cost_report, federated_payload, link_time_s

__all__ = ["cost_report", "federated_payload", "link_time_s"]
