"""The methods, one LightningModule each (KNN, GRaF, KNN-DL, NeRF2, RF Gaussian splatting), on the evaluation
protocol they share (:mod:`.base`)."""
