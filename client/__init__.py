"""swarmloc client: dataset format, synthetic route world, transports, replay and reports."""
