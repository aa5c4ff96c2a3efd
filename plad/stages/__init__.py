"""DVC stage entry points: each is a thin ``main()`` around a pure function.

Prefect flows (``flows/``) call the same functions, so each step has one
implementation.
"""
