"""Studies that reproduce the thesis' figures: not part of the training pipeline.

- :mod:`.anm` -- POD-ANM of one problem against full Newton (``hapticrom anm``, ch. 3).
- :mod:`.cutting` -- limbal relaxing incision, reduced + patch vs the cut meshed (§4.5.1).
"""
