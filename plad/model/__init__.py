"""The network p(z|x) and what reads it: the model, its checkpoints, decoding (beam search) and sampling.

Layer: above ``plad.domains``; below ``plad.rewrite`` and ``plad.learn``.
"""
