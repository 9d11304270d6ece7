"""drivesim's PyTorch reference: the model every parity claim rests on (``model``), its trainers
(``train``: ``vae_gan``, ``sequences``, ``train_heads``, ``train_texture``; ``distributed`` and
``checkpoints`` beside them), the exporter (``export``), the test fixtures (``fixtures``), the
evaluation (``evaluation``, ``futures``) and the timings against the crate (``compare``,
``compare_train``). It imports the ``drivesim`` package (episodes files, the steering probe) as
an installed package; ``weights/tool`` runs its commands (``python -m drivesim_reference.CMD``).
"""
