"""Training: losses, the shared loop (DDP through torchrun), pretraining and supervised training."""
