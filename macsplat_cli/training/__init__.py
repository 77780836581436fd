"""Training of the pair predictor (``macsplat train``): the data (:mod:`.data`), the model, the objective."""
