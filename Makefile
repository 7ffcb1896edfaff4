# Two commands: `make demo` runs the main job, `make test` runs the test suite.  Both set up .venv first.
# `make docs` builds the documentation site.
VENV ?= .venv
PY := $(VENV)/bin/python
export MPLBACKEND := Agg
export VTK_DEFAULT_OPENGL_WINDOW := vtkEGLRenderWindow
export PYVISTA_OFF_SCREEN := true

.PHONY: setup demo test slow study docs clean
setup:
	@bash scripts/setup.sh $(VENV)

demo: setup
	$(PY) demos/run_all.py

study: setup
	$(PY) demos/06_study.py

# two worker processes (pytest-xdist): the suite is many independent single-threaded tests
test: setup
	$(PY) -m pytest -q -n 2 --durations=25

slow: setup
	$(PY) -m pytest -q -m slow

# The documentation site (docs/_build/html): warnings are errors; the quick demos run for the gallery.
docs:
	@bash scripts/setup.sh $(VENV) all,test,docs
	@rm -f docs/_build/html/index.html
	$(PY) -m sphinx -W --keep-going -b html docs docs/_build/html
	@test -f docs/_build/html/index.html || { echo "docs: sphinx stopped before writing index.html" >&2; exit 1; }

clean:
	rm -rf $(VENV) out .pytest_cache docs/_build docs/api/generated docs/gallery demos/out
