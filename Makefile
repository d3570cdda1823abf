# The two commands of the README: `make demo` (main job on a built-in default) and
# `make test` (the test suite). Both install what a fresh Debian 12 machine lacks.
.PHONY: demo test bootstrap lint bench fixtures validation

bootstrap:
	@bash scripts/bootstrap.sh

demo: bootstrap
	cargo run --release --quiet -- demo

# The tests also open a report in headless Chromium (tests/report_chromium.rs), then
# build and test the Python package (scripts/python_test.sh).
test:
	@bash scripts/bootstrap.sh --chromium --python
	cargo test --no-fail-fast
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
