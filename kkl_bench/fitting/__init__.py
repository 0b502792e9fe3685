"""What fits share beyond the plugin face: settings chosen on validation streams
(:mod:`.tuning`) and the nominal model calibrated on logged data (:mod:`.calibration`).

Layer: imports the plugin face (estimator, training), support, the suite, the measurement
model, the registry and the protocol."""
