"""Importable worked examples (the paper's beam, ...)."""
