"""The simulated AFM-in-SEM: sample surfaces, drift and stage errors, synthetic patch sets."""
