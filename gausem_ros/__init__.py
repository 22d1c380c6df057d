"""GauSem's ROS 2 layer: nodes, the bag/dataset player, QoS, TF, time synchronisation and bag IO helpers.

Message conversions live in ``msg_adapters``; this package parses parameters, converts and calls the core.
"""
import gausem_core  # noqa: F401 (first: its OpenMP setting must precede torch's import)
