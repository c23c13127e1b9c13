# Two commands do all the set-up on a fresh machine:
#   make demo   installs everything and runs the main job on the embedded synthetic scene
#   make test   installs everything and runs the test suite
# CPU machines get the CPU build of torch (TORCH=torch==2.13.0). GPU users pick the CUDA build, e.g.
#   make demo TORCH="torch==2.13.0" PIP_EXTRA="--extra-index-url https://download.pytorch.org/whl/cu126"
PY ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
PIP_EXTRA ?=
OUT ?= outputs/demo
SEED ?= 0
# optional extras installed with the package: test (the suite), ray (eval --ray and its test); EXTRAS=test skips Ray
EXTRAS ?= test,ray

.PHONY: install demo test clean

install: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml Makefile
	$(PY) -m venv $(VENV)
	$(VENV)/bin/python -m pip install -q --upgrade pip
	# torch is pinned in the SAME command as the rest so no dependency can pull a CUDA build.
	$(VENV)/bin/python -m pip install -q $(PIP_EXTRA) "$(TORCH)" -e ".[$(EXTRAS)]"
	touch $@

demo: install
	$(VENV)/bin/lipmap-loc eval --dataset synthetic --seed $(SEED) --out $(OUT)

test: install
	$(VENV)/bin/python -m pytest -q -ra

clean:
	rm -rf $(VENV) outputs
