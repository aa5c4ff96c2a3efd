"""Data: the real datasets (fetched and checked), prepared target files, user inputs, batching.

Layer: above the core modules (``plad.errors``, ``plad.fsutil``, ``plad.config``, ``plad.layout``) and
``plad.metrics``; below ``plad.domains``, which declare their target data with these types.
"""
