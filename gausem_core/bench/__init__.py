"""The SLAM benchmark harness behind ``gausem bench slam``: suites (:mod:`.suite`), one run per process
(:mod:`.worker`), the Open3D baselines (:mod:`.baselines`, open3d imported only when they run) and the paper-shaped
Markdown tables (:mod:`.tables`)."""
