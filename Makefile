# maniskill_torchrl developer targets. Run `make` for help.
.DEFAULT_GOAL := help
.PHONY: help setup test demo bench clean gpu-kit

VENV        := .venv
PYTEST_ARGS ?=
DEMO_ARGS   ?=

help:
	@echo "Targets:"
	@echo "  make setup   create .venv and install the package (+ test, demo extras); checks Vulkan"
	@echo "  make test    run the test suite (PYTEST_ARGS=... passed to pytest)"
	@echo "  make demo    run the demo CLI (DEMO_ARGS=... passed to 'maniskill-torchrl demo')"
	@echo "  make bench   run benchmarks/run_all.py"
	@echo "  make gpu-kit fill .gpu/ with the wheels and .debs for the GPU checks (benchmarks/README.md)"
	@echo "  make clean   remove .venv and outputs/"

setup:
	@bash scripts/setup.sh

test: setup
	$(VENV)/bin/python -m pytest -q tests $(PYTEST_ARGS)

demo: setup
	$(VENV)/bin/maniskill-torchrl demo $(DEMO_ARGS)

bench: setup
	$(VENV)/bin/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) outputs/

gpu-kit:
	@bash scripts/gpu_kit.sh
