"""Learning and deciding: classifiers on tactile sequences, experiments, the command line."""
