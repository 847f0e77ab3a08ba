"""The estimators (DPSO ours and the papers', PF-g/PF-l), pure: they see the map only through
callbacks."""
