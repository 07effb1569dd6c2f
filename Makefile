# Two commands do all the set-up: `make demo` and `make test`. Both create .venv when missing.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
# The kernels' cache is keyed on the reconstruction sources (reconstruction/kernel_cache.py): compile again when they change.
WARM := $(VENV)/.kernels
KERNEL_SOURCES := $(shell find reconstruction -name '*.py')
# What the page imports from the npm packages, and their licences.
VENDOR := deploy/web/vendor
VENDORED := three/LICENSE three/build/three.module.js three/build/three.core.js three/examples/jsm/loaders/GLTFLoader.js \
	three/examples/jsm/utils/BufferGeometryUtils.js three/examples/jsm/controls/OrbitControls.js three/examples/jsm/postprocessing/Pass.js \
	@sparkjsdev/spark/LICENSE @sparkjsdev/spark/dist/spark.module.js

.PHONY: env demo test bench clean

env: $(WARM)

# Reinstall only when the dependency list (or this recipe) changes, so a second call is fast.
$(STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	# torch first, pinned, so nothing later can pull a CUDA build.
	$(PY) -m pip install --quiet "torch==2.13.0"
	$(PY) -m pip install --quiet -e ".[test,cluster]"
	# The Khronos glTF validator checks the GLB export in the tests (npm registry); without it they skip and say so.
	@command -v npm >/dev/null && npm install --silent --no-audit --no-fund --prefix $(VENV)/node gltf-validator@2.0.0-dev.3.10 \
		|| echo "gltf-validator not installed (npm or its registry unavailable): the GLB validation test will skip"
	# The page of `cadsplat view` (deploy/view.py): three.js and Spark from npm, copied into the package so it runs offline.
	@command -v npm >/dev/null && npm install --silent --no-audit --no-fund --prefix $(VENV)/node three@0.181.0 @sparkjsdev/spark@2.2.0 \
		&& rm -rf $(VENDOR) && mkdir -p $(VENDOR) && cd $(VENV)/node/node_modules && cp --parents $(VENDORED) $(CURDIR)/$(VENDOR) \
		|| echo "three.js and Spark not installed (npm or its registry unavailable): cadsplat view and its browser tests will not run"
	# Babylon.js, the browser tests' reader of the KHR_gaussian_splatting GLB (tests only: not copied into the package).
	@command -v npm >/dev/null && npm install --silent --no-audit --no-fund --prefix $(VENV)/node babylonjs@9.28.0 babylonjs-loaders@9.28.0 \
		|| echo "Babylon.js not installed (npm or its registry unavailable): the KHR GLB browser test will skip"
	# Headless Chromium for the browser tests (Debian's package, where apt and root are at hand); without it they skip and say so.
	@command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && apt-get update -qq \
		&& apt-get install -y -qq chromium >/dev/null; } || echo "chromium not installed: the browser tests will skip"
	touch $(STAMP)

# Compile every numba kernel (training, registration, inspection) into its on-disk cache now, not in the first twin.
$(WARM): $(STAMP) $(KERNEL_SOURCES)
	$(PY) -m reconstruction.warmup
	touch $(WARM)

demo: env
	$(VENV)/bin/cadsplat demo

test: env
	$(PY) -m ruff check .
	$(PY) -m ruff format --check .
	$(PY) -m pytest -n 2 --timeout=900 -q

# The quick benchmarks (minutes; no shared data needed): each rewrites its table in benchmarks/results/.
# The others: python -m benchmarks.bench_<thing> --help.
bench: env
	$(PY) -m benchmarks.bench_acquisition
	$(PY) -m benchmarks.bench_calibration

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
