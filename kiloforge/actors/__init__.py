"""Actor kinds: one module per network family (mlp, gru, lstm) over one interface (:mod:`.base`),
looked up by name in :mod:`.registry`."""
