"""Actor kinds: one module per family (mlp, gru, lstm and the hand-written searcher) over one interface (:mod:`.base`),
looked up by name in :mod:`.registry`."""
