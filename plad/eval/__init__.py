"""Evaluation and its outputs: the one-box floor, the results report (table, plots) and pictures.

Layer: above ``plad.learn``; below ``plad.tracking`` users (the stages, ``plad.serve``).
"""
