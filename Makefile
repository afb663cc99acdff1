# The two commands of README.md.  Both create or reuse .venv in the repository root.
.PHONY: demo test venv bench

venv:
	@bash scripts/venv.sh

demo: venv
	.venv/bin/dynastereo demo

test: venv
	.venv/bin/python -m pytest -q

bench: venv
	@for b in benchmarks/bench_*.py; do echo "== $$b"; .venv/bin/python $$b || exit 1; done
