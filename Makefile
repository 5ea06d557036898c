# One task runner for the README, CI and developers. Everything lives in ./.venv.
VENV   ?= .venv
PY     := $(VENV)/bin/python
export VIRTUAL_ENV := $(abspath $(VENV))
export PATH := $(abspath $(VENV))/bin:$(PATH)

.PHONY: setup demo test lint fmt rust-test py-test bench clean

$(VENV)/bin/activate:
	python3 -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip maturin

# Build the Rust extension (release) and install decod_rs with its dev extras.
setup: $(VENV)/bin/activate
	$(VENV)/bin/maturin develop --release --extras dev,batch

demo: setup
	$(VENV)/bin/decod demo

fmt:
	cargo fmt --all
	$(VENV)/bin/ruff format python tests
	$(VENV)/bin/ruff check --fix python tests

# Clippy in the release profile: the build scripts, proc macros and C libraries (SQLite, zstd,
# lz4) of `make setup`'s release build are reused instead of rebuilt for the dev profile (the
# code has no cfg(debug_assertions)): 7.0 -> 2.1 min on a fresh two-core machine.
lint: setup
	cargo fmt --all -- --check
	cargo clippy --release --all-targets -- -D warnings
	cargo clippy --release --all-targets --features python -- -D warnings
	$(VENV)/bin/ruff check python tests
	$(VENV)/bin/ruff format --check python tests
	$(VENV)/bin/mypy
	$(PY) -m mypy.stubtest decod_rs._core --allowlist .stubtest-allowlist

# The release profile and Cargo.toml's feature pins let this reuse `make setup`'s build of faer,
# gemm and nalgebra: only decod and the dev-dependencies are compiled (4.4 -> 2.0 min in CI).
rust-test:
	cargo test --release

# One test module per worker (its shared logs are module fixtures); the slowest tests named.
py-test: setup
	$(PY) -m pytest -q -n logical --dist loadfile --durations=10

test: lint rust-test py-test

bench: setup
	cargo bench
	$(PY) -m pytest -q tests/benchmarks --benchmark-enable

clean:
	rm -rf $(VENV) target
