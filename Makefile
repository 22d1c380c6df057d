# Two commands on a fresh machine: `make demo` and `make test` (each sets up .venv first, once).
PYTHON ?= python3
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
PY := $(VENV)/bin/python
PIP := $(PY) -m pip --disable-pip-version-check
STAMP := $(VENV)/.installed
PYTEST_ARGS ?=
DEMO_OUT ?= out/demo

.PHONY: setup test test-slow test-all test-orders demo bench clean

setup: $(STAMP)

$(STAMP): requirements.txt requirements-dev.txt requirements-tf.txt constraints.txt setup.py tools/build_tf2_msgs.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q "$(TORCH_SPEC)"
	$(PIP) install -q -r requirements-dev.txt -c constraints.txt
	$(PIP) install -q --no-deps --no-build-isolation -e .
	tools/build_tf2_msgs.sh $(VENV)  # /tf on the pip path: tf2_msgs/TFMessage, unless importable (15-35 s)
	$(VENV)/bin/gausem info  # also compiles the C++ CPU renderer (once per machine)
	touch $@

# `make test`: the fast selection (tests not marked slow); `make test-slow` the rest; CI runs both and `test-orders`.
test: $(STAMP)
	$(PY) -m pytest -m "not slow" $(PYTEST_ARGS)

test-slow: $(STAMP)
	$(PY) -m pytest -m slow $(PYTEST_ARGS)

test-all: $(STAMP)
	$(PY) -m pytest $(PYTEST_ARGS)

# The tests that compare floating-point results across implementations, again with other summation orders forced: torch's
# scalar CPU kernels (no vector lanes) on one thread, and its AVX2 kernels on three, as other CPUs would sum. Their
# bounds come from the arithmetic (test/rounding.py), so they hold whatever the order.
PARITY_TESTS := test/test_fused_alignment.py test/test_direct_alignment.py test/test_device_alignment.py \
	test/test_render.py test/test_depth_filter.py test/test_devices.py
test-orders: $(STAMP)
	ATEN_CPU_CAPABILITY=default OMP_NUM_THREADS=1 $(PY) -m pytest -q -m "not slow" $(PARITY_TESTS) $(PYTEST_ARGS)
	ATEN_CPU_CAPABILITY=avx2 OMP_NUM_THREADS=3 $(PY) -m pytest -q -m "not slow" $(PARITY_TESTS) $(PYTEST_ARGS)

# The ROS 2 node suite end to end: the synthetic sequence of `gausem demo` (30 frames, 160x120) as a ROS 2 bag, replayed
# in lock-step to all nodes in one process, evaluated like `gausem run` (summary on the terminal, outputs in DEMO_OUT).
# `gausem demo --out DIR` is the offline counterpart. ROS domain 42 (unless ROS_DOMAIN_ID is set), local host only.
demo: $(STAMP)
	rm -rf $(DEMO_OUT)/synthetic_bag
	$(VENV)/bin/gausem-bag synthetic $(DEMO_OUT)/synthetic_bag --size 160x120 --max-frames 30
	ROS_DOMAIN_ID=$${ROS_DOMAIN_ID:-42} ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST $(VENV)/bin/gausem-ros \
	  $(DEMO_OUT)/synthetic_bag --lockstep --rate 0 --timeout 120 --report $(DEMO_OUT) --reference synthetic \
	  --ros-args --params-file params/synthetic.yaml

# Benchmark-only packages (open3d for the baselines) go into .venv first. BENCH_SUITES: the SLAM suites to run
# (GauSem's rows take hours on a CPU; e.g. `make bench BENCH_SUITES=benchmarks/suites/smoke.yaml` for a check).
bench: BENCH_SUITES ?= benchmarks/suites/paper.yaml benchmarks/suites/ablation.yaml
bench: $(STAMP)
	$(PIP) install -q -r requirements-bench.txt -c constraints.txt
	$(PY) benchmarks/bench.py render --out benchmarks/results
	for suite in $(BENCH_SUITES); do $(PY) benchmarks/bench.py slam --suite $$suite --out benchmarks/results || exit 1; done
	$(PY) benchmarks/bench.py report

clean:
	rm -rf $(VENV) out .pytest_cache
