"""The learned occupancy model's offline pipeline, which drives the simulator and the mapper
together: walks through the suite's scenes (:mod:`.walks`), training (:mod:`.training`,
``rovergate train``) and evaluation against ground truth (:mod:`.evaluate`, ``rovergate
eval-model``). The model itself, its engines and weights stay in ``mapper/``."""
