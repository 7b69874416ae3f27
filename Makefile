# maniskill_torchrl developer targets. Run `make` for help.
.DEFAULT_GOAL := help
.PHONY: help setup test test-pictures test-slow test-examples test-sota test-readme test-ray test-model test-upstream test-cuda-double test-registry test-nightly lint docs demo bench clean gpu-kit gpu-check

# MANISKILL=release (default: mani-skill 3.0.x, in .venv) or nightly (mani-skill-nightly, in .venv-nightly).
MANISKILL   ?= release
ifeq ($(MANISKILL),nightly)
VENV        := .venv-nightly
else
VENV        := .venv
endif
# Python writes the bytecode of each module it imports without one (set-up compiles what the library
# imports; this covers the rest and the repository's own files), where a machine sets
# PYTHONDONTWRITEBYTECODE: otherwise every test process compiles them again.
unexport PYTHONDONTWRITEBYTECODE
PYTEST_ARGS ?=
DEMO_ARGS   ?=
# pytest-xdist (the `test` extra): WORKERS worker processes, one per core of the CI machine (2). In `make test`
# a test file runs whole in one worker (loadfile), so that its module fixtures (envs, worker pools, subprocess
# runs) are built once; the registry's and upstream's tests are independent (load). WORKERS=1: one process.
WORKERS     ?= 2
# --no-loadscope-reorder: files in collection order (tests/conftest.py puts the slowest first), not by count.
xdist        = $(if $(filter-out 0 1,$(WORKERS)),-n $(WORKERS) --dist $(1) --no-loadscope-reorder)

help:
	@echo "Targets:"
	@echo "  make setup   create .venv and install the package (+ test, demo, distributed, docs, hydra, maniskill extras); checks Vulkan"
	@echo "  make test    run the test suite, in 2 processes (PYTEST_ARGS=... passed to pytest; WORKERS=1: serially)"
	@echo "  make test-pictures  the tests that render (rgb, from_pixels, render()), left out of make test (-m pictures, ~1 min)"
	@echo "  make test-slow  the suite's slowest tests (fresh interpreters, collectors' workers), left out of make test (-m slow, ~1.5 min)"
	@echo "  make test-examples  the examples end to end, as users run them: the demo CLI, PPO, SAC, BC, evaluation, TorchRL's trainers (tests/examples, ~2.5 min)"
	@echo "  make test-sota  TorchRL's own sota trainer scripts (tests/configs/sota), unmodified, on ManiSkill, and a live env in every collector (tests/examples/test_sota_trainers.py, ~6 min)"
	@echo "  make test-readme  the README walked as a newcomer: fresh venv from the wheel, each command from a temp folder (~8 min)"
	@echo "  make test-ray  TorchRL's Ray collectors over the library's envs, on a local Ray instance (tests/examples/test_ray.py, ~4 min on 2 cores)"
	@echo "  make test-model  the model-based test of the asynchronous path, long profile (hypothesis, 5-15 min)"
	@echo "  make test-upstream  the TorchRL pull request of upstream/ on a copy of the installed torchrl (tests/upstream, ~1.5 min)"
	@echo "  make test-cuda-double  the library on a CUDA machine, under the CUDA double (tests/gpu/test_cuda_machine.py, ~2.5 min)"
	@echo "  make test-registry  every task of ManiSkill's registry whose assets are here (tests/registry, ~2 min)"
	@echo "               MANISKILL=nightly: against mani-skill-nightly, in .venv-nightly (= make test-nightly)"
	@echo "  make lint    ruff check + ruff format --check"
	@echo "  make docs    build the docs site into docs/_build/html (warnings are errors), then run every"
	@echo "               Python block of README.md and docs/ (sybil) and the site checks (tests/docs)"
	@echo "  make demo    run the demo CLI (DEMO_ARGS=... passed to 'maniskill-torchrl demo')"
	@echo "  make bench   run every benchmark (python -m benchmarks.run_all)"
	@echo "  make gpu-kit fill .gpu/ with the wheels and .debs for the GPU checks (benchmarks/README.md)"
	@echo "  make gpu-check  dry run here of scripts/gpu_check.py, the accelerator machine's check: no kit,"
	@echo "               .venv as it is, 2 suite workers, a short sweep, a few test files (GPU_CHECK_SUITE)"
	@echo "  make clean   remove .venv, .venv-nightly and outputs/"

setup:
	@MANISKILL=$(MANISKILL) bash scripts/setup.sh

# Their own targets, so that `make test` stays inside 5 minutes on 2 cores: the examples end to end
# (subprocesses as users start them, each importing torch, TorchRL and ManiSkill and computing SAPIEN's
# render tables for its videos: about 2.5 minutes of CPU), the CUDA-double cases (a pytest subprocess
# of their own, tests/gpu/test_cuda_machine.py) and Ray's (a local Ray instance whose actors each
# import torch, TorchRL and ManiSkill: over a minute of CPU on 2 cores). CI runs them all.
SUITE = tests --ignore=tests/registry --ignore=tests/docs --ignore=tests/gpu/test_cuda_machine.py --ignore=tests/upstream \
	--ignore=tests/examples --ignore=tests/readme
test: setup lint
	$(VENV)/bin/python -m pytest -q --durations=15 $(call xdist,loadfile) $(SUITE) -m "not pictures and not slow" $(PYTEST_ARGS)

# The suite's slowest tests (marker `slow`): each starts fresh interpreters or collectors' worker processes,
# which import torch, TorchRL and ManiSkill (10-40 s a test on 2 cores; about 1.5 minutes of the suite).
test-slow: setup
	$(VENV)/bin/python -m pytest -q --durations=5 $(call xdist,loadfile) $(SUITE) -m "slow and not pictures" $(PYTEST_ARGS)

# The suite's tests that render (marker `pictures`): SAPIEN's render tables cost seconds of CPU in
# each process that renders (Mesa's lavapipe here), about a minute of the suite on 2 cores.
test-pictures: setup
	$(VENV)/bin/python -m pytest -q --durations=5 $(call xdist,loadfile) $(SUITE) -m pictures $(PYTEST_ARGS)

test-examples: setup
	$(VENV)/bin/python -m pytest -q --durations=10 $(call xdist,loadfile) tests/examples --ignore=tests/examples/test_ray.py \
		--ignore=tests/examples/test_sota_trainers.py $(PYTEST_ARGS)

# TorchRL's sota trainer scripts as a user runs them (subprocesses with timeouts: a hang fails, never blocks CI);
# each run is a process tree of TorchRL's workers, each importing torch, TorchRL and ManiSkill.
test-sota: setup
	$(VENV)/bin/python -m pytest -q --durations=10 $(call xdist,load) tests/examples/test_sota_trainers.py $(PYTEST_ARGS)

# The README as a newcomer walks it (tests/readme): a fresh venv from the built wheel with the README's extras, every
# README command from a temporary folder with its smoke flag (~8 min on 2 cores: each command a fresh process; BC plans its demos).
test-readme: setup
	$(VENV)/bin/python -m pytest -q --durations=10 tests/readme $(PYTEST_ARGS)

test-ray: setup
	$(VENV)/bin/python -m pytest -q --durations=5 tests/examples/test_ray.py $(PYTEST_ARGS)

# upstream/ (upstream/README.md): the module, exports, config and TorchRL's test file applied to a copy of the
# installed torchrl, whose test file then runs in a child process.
# The model-based test of the asynchronous path (tests/engines/test_async_model.py), its long profile: new random
# sequences each run, half of them receiving the answers as they come (make test runs its short, derandomized
# profile; 5-15 min on 2 cores, by load). .ci/run runs it. What hypothesis draws never depends on timing, so that a
# failure replays and shrinks (it failed as FlakyStrategyDefinition when its rules' preconditions did; issue 59).
test-model: setup
	MANISKILL_TORCHRL_MODEL_RUNS=long $(VENV)/bin/python -m pytest -q --durations=5 tests/engines/test_async_model.py $(PYTEST_ARGS)

test-upstream: setup
	$(VENV)/bin/python -m pytest -q --durations=5 $(call xdist,load) tests/upstream $(PYTEST_ARGS)

test-cuda-double: setup
	$(VENV)/bin/python -m pytest -q --durations=5 tests/gpu/test_cuda_machine.py $(PYTEST_ARGS)

test-registry: setup
	$(VENV)/bin/python -m pytest -q -rs --durations=10 $(call xdist,load) tests/registry $(PYTEST_ARGS)

test-nightly:
	@$(MAKE) --no-print-directory test MANISKILL=nightly

lint: setup
	@rc=0; $(VENV)/bin/ruff check . || rc=1; $(VENV)/bin/ruff format --check . || rc=1; \
		$(VENV)/bin/ruff format --check --line-length 88 maniskill_torchrl/envs/maniskill.py || rc=1; exit $$rc

# -E: every page is read again, so a warning is never hidden by an earlier build.
docs: setup
	$(VENV)/bin/sphinx-build -E -W --keep-going -n -q -b html docs docs/_build/html
	$(VENV)/bin/python -m pytest -q --durations=10 README.md docs tests/docs --ignore=docs/_build $(PYTEST_ARGS)

demo: setup
	$(VENV)/bin/maniskill-torchrl demo $(DEMO_ARGS)

bench: setup
	$(VENV)/bin/python -m benchmarks.run_all

clean:
	rm -rf .venv .venv-nightly outputs/

gpu-kit:
	@python3 scripts/gpu_kit.py

GPU_CHECK_SUITE ?= tests/package/test_stack.py tests/envs/test_hang.py tests/package/test_install.py
gpu-check: setup
	$(VENV)/bin/python scripts/gpu_check.py --local outputs/gpu-check --workers 2 --sweep-n 1 2 --sweep-seconds 1 \
		--startup-limit 120 --sweep-s 400 --budget 1200 --suite $(GPU_CHECK_SUITE)
