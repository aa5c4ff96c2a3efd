"""Learning p(z|x): the training loop, supervised pretraining (SP) and its curriculum, data parallelism, the
PLAD rounds (P_BEST, ST, LEST, WS and their mixtures), wake-sleep and the REINFORCE baseline (RL).

Layer: above ``plad.model`` and ``plad.rewrite``; below ``plad.eval``, ``plad.tracking`` and the stages.
"""
