"""The work behind each ``ngp-mi`` sub-command that is not training or evaluation: it reads its
inputs, drives the library, and writes images, sheets and reports (``cli.py`` only parses)."""
