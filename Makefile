# The two commands of README.md (and `make install`).  All create or reuse .venv in the repository root.
.PHONY: demo test venv bench install docs

BINDIR ?= $(HOME)/.local/bin

venv:
	@bash scripts/venv.sh

demo: venv
	.venv/bin/dynastereo demo

test: venv
	.venv/bin/python -m pytest -q

bench: venv
	@for b in benchmarks/bench_*.py; do echo "== $$b"; .venv/bin/python $$b || exit 1; done

# the documentation site into site/ (docs/development.md): the generated pages first
docs: venv
	.venv/bin/python scripts/gen_docs.py
	.venv/bin/mkdocs build --strict

# `dynastereo` on your PATH: a symlink $(BINDIR)/dynastereo -> .venv/bin/dynastereo
install: venv
	@mkdir -p "$(BINDIR)"
	ln -sf "$(CURDIR)/.venv/bin/dynastereo" "$(BINDIR)/dynastereo"
	@case ":$$PATH:" in *":$(BINDIR):"*) ;; *) echo "note: $(BINDIR) is not on your PATH";; esac
