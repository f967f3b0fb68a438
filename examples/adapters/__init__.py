"""Worked examples of instrument adapters (see docs/instruments.md)."""
