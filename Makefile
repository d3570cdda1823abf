# The two commands of the README: `make demo` (main job on a built-in default) and
# `make test` (the test suite). Both install what a fresh Debian 12 machine lacks.
.PHONY: demo test bootstrap lint bench fixtures validation fuzz fuzz-doc

bootstrap:
	@bash scripts/bootstrap.sh

demo: bootstrap
	cargo run --release --quiet -- demo

# The tests also open a report in headless Chromium (tests/report_chromium.rs), then
# build and test the Python package (scripts/python_test.sh). --slurm: slurm-wlm and
# munge for the one-node Slurm cluster of tests/slurm_cluster.rs. A release build: the
# diagnosis tests fit campaigns and run about twice as fast as in the test profile.
# The tests too long for this command are marked #[ignore] and run by
# `make validation PAGES=long_tests` (docs/validation/long_tests.md).
test:
	@bash scripts/bootstrap.sh --chromium --python --slurm
	cargo test --release --no-fail-fast
	@bash scripts/python_test.sh

lint: bootstrap
	cargo fmt --check
	cargo clippy --all-targets -- -D warnings
	RUSTDOCFLAGS="-D warnings" cargo doc --no-deps

bench: bootstrap
	cargo bench

fixtures: bootstrap
	cargo run --example make_fixtures -- fixtures

# The validation pages under docs/validation/ (every page, or PAGES="floor bench matrix";
# BENCH_ARGS=--quick, MATRIX_ARGS="--size 64 ..." as scripts/validation.sh says).
validation: bootstrap
	@bash scripts/validation.sh $(PAGES)

# The mutation fuzzer over every reader, against the real stage (docs/operations.md):
# 100,000 mutants; fuzz-doc regenerates the figures of docs/operations.md.
fuzz: bootstrap
	cargo run --release --quiet -- fuzz --mutants 100000 --seed 1 --batch 200 --stage-checkpoints 100

fuzz-doc: bootstrap
	cargo run --release --quiet -- fuzz --mutants 1000 --seed 2 --batch 100 --stage-checkpoints 8 --markdown-into docs/operations.md
