"""Checks that `python -m bench.consumers` runs inside each consumer's scratch venv, with the
consumer's own code (unmodified) on sys.path. They import no rigd module (rigd is not installed
there): what they compare against is written by the harness as plain files (`reference.npz`,
`views.json`). Each prints its findings and exits non-zero on the first failed check."""
