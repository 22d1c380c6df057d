"""GauSem core: ROS-free semantic Gaussian-splatting SLAM (torch + numpy). Never imports rclpy or *_msgs."""

__version__ = "0.1.0"
