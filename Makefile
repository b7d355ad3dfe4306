# earcore: the README's two commands are `make demo` and `make test`.
# Every target sets up what it needs (virtual environment, release build, packages).
# `make help` lists the targets.

SHELL := /bin/bash
.SHELLFLAGS := -euo pipefail -c
PYTHON ?= python3
VENV := .venv
TEST_VENV := .venv-test
PY := $(VENV)/bin/python
PIP_FLAGS := --disable-pip-version-check -q
LINT_TOOLS := "ruff>=0.17,<0.18" "mypy>=1.10"
export PIP_CACHE_DIR ?= $(HOME)/.cache/pip

.PHONY: help demo pose bench-pose bench-transfer map-demo test test-rust test-python develop wheel bench bench-python lint fuzz clean system-deps

help: ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | awk -F':.*## ' '{printf "  make %-14s %s\n", $$1, $$2}'

system-deps: ## Debian packages the build needs (only installed when missing)
	@command -v cargo >/dev/null || { echo "Rust (cargo) is required: https://rustup.rs"; exit 1; }
	@$(PYTHON) -c 'import ensurepip, venv' 2>/dev/null || { \
	  echo "installing python3-venv"; (apt-get update -qq && apt-get install -y -qq python3-venv) >/dev/null; }

$(VENV)/.ready: pyproject.toml | system-deps
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install $(PIP_FLAGS) --upgrade pip
	$(PY) -m pip install $(PIP_FLAGS) "maturin>=1.8,<2" numpy
	$(PY) -m pip install $(PIP_FLAGS) "matplotlib>=3.7" "pyoctomap>=1.2" "pybullet>=3.2" "example-robot-data>=6" "rerun-sdk>=0.41" "ompl>=2,<3" "opencv-python-headless>=4.9,<5" "pyyaml>=6"
	$(PY) -m pip install $(PIP_FLAGS) $(LINT_TOOLS)
	touch $@

# Training the networks: torch from PyPI (the CUDA build, ~3.3 GB of downloads, runs on the CPU).
$(VENV)/.learning: $(VENV)/.ready
	$(PY) -m pip install $(PIP_FLAGS) "torch>=2.2" "onnx>=1.15" "onnxruntime>=1.17" "tqdm>=4.60" "ray>=2.40"
	touch $@

develop: $(VENV)/.ready ## build the extension (release) into .venv, editable
	$(VENV)/bin/maturin develop --release -q

demo: develop ## the main job: the simulated cell (UR5, 4 cameras, a person reaching in) -> out/ PNGs + summary.json
	$(VENV)/bin/earcore run --out out

pose: develop $(VENV)/.learning ## robot pose from one colour image, small: images, training, evaluation, ONNX -> out/pose (~6 min)
	$(VENV)/bin/earcore dataset robots --out out/robots --scale 0.5 --quiet
	$(VENV)/bin/earcore dataset robots --out out/robots-heldout --scale 0.1 --seed 1001 --quiet
	$(VENV)/bin/earcore train pose --data out/robots --out out/pose --minutes 5 --no-progress
	$(VENV)/bin/earcore evaluate pose --checkpoint out/pose --data out/robots-heldout --split all --out out/pose/heldout
	$(VENV)/bin/earcore export pose --checkpoint out/pose --out out/pose/pose.onnx

map-demo: develop ## the quick map demo (synthetic scene, 3 cameras, danger decay) -> out/map_danger.png
	$(VENV)/bin/earcore demo --out out

wheel: $(VENV)/.ready ## build the release wheel into dist/
	rm -rf dist
	$(VENV)/bin/maturin build --release -q -o dist

test-rust: system-deps ## Rust unit, integration and doc tests of the core
	cargo test -q --release

test-python: wheel ## install the wheel into a fresh venv and run pytest against it
	$(PYTHON) -m venv --clear $(TEST_VENV)
	$(TEST_VENV)/bin/python -m pip install $(PIP_FLAGS) --upgrade pip
	$(TEST_VENV)/bin/python -m pip install $(PIP_FLAGS) "$$(ls dist/earcore-*.whl)[test]"
	cd tests && ../$(TEST_VENV)/bin/python -m pytest -q -p no:cacheprovider .

test: lint test-rust test-python ## every test: rustfmt + clippy + ruff + mypy, cargo test (core), pytest (installed wheel)

bench: develop ## criterion benches, then the side-by-side comparisons with OctoMap and FCL
	cargo bench
	$(MAKE) bench-python

bench-pose: develop $(VENV)/.learning ## labelled-image speed; the three pose networks, 60 min each with their data, side by side; ships the keypoint network (~3.5 h)
	$(PY) benches/dataset_generation.py
	$(VENV)/bin/earcore dataset robots --out benches/out/data/ur --quiet
	$(VENV)/bin/earcore dataset robots --out benches/out/data/ur-random --mode random --count 2000 --seed 7 --quiet
	$(VENV)/bin/earcore dataset robots --out benches/out/data/ur-heldout --seed 1001 --scale 0.2 --quiet
	$(PY) benches/pose_accuracy.py --data benches/out/data/ur --extra benches/out/data/ur-random --heldout benches/out/data/ur-heldout \
	  --minutes 57 --refine --out benches/out/pose --ship keypoint

bench-transfer: develop $(VENV)/.learning ## Papers VI-VII from bench-pose's UR network, and the loss combiners over 8 runs each (~2 h)
	@test -f benches/out/pose/multi/checkpoint.pt || { echo "make bench-pose first: its UR network is the source"; exit 1; }
	$(VENV)/bin/earcore dataset robots --out benches/out/data/iiwa --robots iiwa --seed 11 --quiet
	$(VENV)/bin/earcore dataset robots --out benches/out/data/mixed --robots ur3,ur5,ur10,iiwa,panda --count 400 --seed 12 --quiet
	$(VENV)/bin/earcore dataset robots --out benches/out/data/ur64 --size 64x53 --seed 13 --quiet
	$(PY) benches/pose_transfer.py --source benches/out/pose/multi --ur benches/out/data/ur --iiwa benches/out/data/iiwa \
	  --new benches/out/data/mixed --new-robots iiwa,panda --out benches/out/transfer
	$(PY) benches/loss_combiners.py --data benches/out/data/ur64 --runs 8 --steps 500 --batch 16 --eval-every 20 --jobs 2 --out benches/out/combiners

bench-python: develop ## only the side-by-side comparisons (vs pyoctomap, python-fcl, open3d-cpu + pyoctomap, small_gicp)
	@ldconfig -p | grep -q libusb-1.0 || { echo "installing libusb-1.0-0 (open3d needs it)"; \
	  (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null; }
	$(PY) -m pip install $(PIP_FLAGS) "python-fcl>=0.7" "open3d-cpu>=0.19" "small_gicp>=1.0" "kiss-icp>=1.2"
	$(PY) benches/bench_vs_octomap.py
	$(PY) benches/bench_robot_vs_fcl.py
	$(PY) benches/bench_perception.py
	$(PY) benches/bench_preprocess.py
	$(PY) benches/bench_icp_iteration.py
	$(PY) benches/bench_icp_vs_peers.py
	$(PY) benches/bench_icp_matrix.py
	$(PY) benches/bench_surface_map.py
	$(PY) benches/bench_render.py

lint: $(VENV)/.learning ## rustfmt, clippy (missing docs included), ruff, mypy
	cargo fmt --all --check
	cargo clippy --workspace --all-targets -q -- -D warnings
	$(VENV)/bin/ruff check python tests benches
	$(VENV)/bin/mypy

fuzz: ## fuzz the .bt/.ot readers for 10 minutes each (needs cargo-fuzz)
	command -v cargo-fuzz >/dev/null || cargo install cargo-fuzz
	cd fuzz && RUSTC_BOOTSTRAP=1 cargo fuzz run read_binary -- -max_total_time=600
	cd fuzz && RUSTC_BOOTSTRAP=1 cargo fuzz run read_full -- -max_total_time=600

clean: ## remove build outputs and virtual environments
	rm -rf target dist out $(VENV) $(TEST_VENV) fuzz/target
