# Two commands: `make demo` runs the main job, `make test` runs the test suite.  Both set up .venv first.
VENV ?= .venv
PY := $(VENV)/bin/python
export MPLBACKEND := Agg
export VTK_DEFAULT_OPENGL_WINDOW := vtkEGLRenderWindow
export PYVISTA_OFF_SCREEN := true

.PHONY: setup demo test slow study clean
setup:
	@bash scripts/setup.sh $(VENV)

demo: setup
	$(PY) demos/run_all.py

study: setup
	$(PY) demos/06_study.py

test: setup
	$(PY) -m pytest -q

slow: setup
	$(PY) -m pytest -q -m slow

clean:
	rm -rf $(VENV) out .pytest_cache
