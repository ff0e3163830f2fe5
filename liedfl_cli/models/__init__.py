"""Models: LieDFLNN and (later) the paper's baselines, built by `build_model`."""
