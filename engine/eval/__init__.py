"""Speed against error: the evaluation protocol, image metrics, tables and plots."""
