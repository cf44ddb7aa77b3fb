"""The numerical-stability suite (docs/architecture.md "Numerical stability"); see ``cases.py``."""
