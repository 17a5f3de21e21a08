# The two commands a newcomer types: `make demo` (the main job) and `make test`.
# Both run `make setup` first, which installs everything and is a no-op when nothing changed.
SHELL := /bin/bash
.PHONY: setup lint test demo bench clean

setup:
	@bash scripts/setup.sh

# ruff (ruff.toml): the linter and the formatter's check, over every Python file and the Python
# blocks of the Markdown documents. `.venv/bin/ruff format .` writes what the check wants.
lint: setup
	@.venv/bin/ruff check . && .venv/bin/ruff format --check .

# The lint; the pure-core tests (the sim2real diagnoses are most of the time) on both cores; then
# the ROS graph tests alone, as they wait on nodes and time out under load.
test: lint
	@scripts/with_env.sh python -m pytest test -q -p no:cacheprovider -m 'not ros' -n 2 --dist loadgroup --durations=10
	@scripts/with_env.sh python -m pytest test -q -p no:cacheprovider -m ros --durations=5

demo: setup
	@scripts/with_env.sh python -m afm_bringup.cli demo --output demo_output

bench: setup
	@scripts/with_env.sh python bench/bench_recording.py
	@scripts/with_env.sh python bench/bench_simulator.py

clean:
	rm -rf build install log .venv demo_output
