"""GauSem core: ROS-free semantic Gaussian-splatting SLAM (torch + numpy). Never imports rclpy or *_msgs.

OpenMP threads (torch's and the compiled kernels') wait passively at barriers unless ``OMP_WAIT_POLICY`` says
otherwise: spinning threads on a machine whose cores are busy with other work (a robot's other nodes, a second run)
slowed the first frame of a 2-thread run on a loaded 2-core machine from 17 s to more than 300 s. This takes effect
only when gausem_core is imported before torch.
"""
import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
