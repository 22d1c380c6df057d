"""The tracking_mapping node's parts (:mod:`gausem_ros.nodes.tracking_mapping` holds the inputs, the call into the
core and the wiring), each in its module: ``frame_input``, ``trajectory``, ``map_outputs``, ``records``,
``loop_link``, ``checkpoints``, ``services``, ``diagnostics``, ``live_view``, ``parameters``. A part reads the core
only through its events and public state (``gausem_core.slam.events``, ``GauSemSLAM``)."""
