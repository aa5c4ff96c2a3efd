"""What users run: the ``plad`` command line, inference on their own shapes and model resolution.

Layer: the top, beside ``plad.stages``.
"""
