"""The learned matcher: the GCN, its checkpoints, losses and training.

- :mod:`.model`: the network (layers, configuration, batching, embedding a problem);
- :mod:`.checkpoint`: weights + configuration, loaded with ``weights_only=True``;
- :mod:`.losses`: reconstruction, epipolar and edge-head losses (training only);
- :mod:`.objective`: samples, batches and the loss of one step;
- :mod:`.sources`: training data (problem files, bags, generated scenes);
- :mod:`.config`, :mod:`.train`, :mod:`.ddp`: the resumable (distributed) training loop.
"""
