"""Benchmarks behind ``meniscope bench``: one module per benchmark, each exposing ``register(subparsers)``.

A benchmark measures one part of the pipeline (speed and quality, side by side in one run)
and writes its figures as JSON plus a Markdown table into the folder it is given.
"""
