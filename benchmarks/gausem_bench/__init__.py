"""GauSem's benchmark harness, behind ``python benchmarks/bench.py`` (:mod:`.cli`) and kept out of the installed library: the renderer
benchmark (:mod:`.render`) and the SLAM benchmark (:mod:`.slam`) with its suites (:mod:`.suite`), one run per process
(:mod:`.worker`), the Open3D baselines (:mod:`.baselines`, open3d imported only when they run), colour resampling for
unregistered depth (:mod:`.color_registration`) and the paper-shaped Markdown tables (:mod:`.tables`)."""
