"""Physics-plant checks and benchmarks (the plant itself is vlr_drake.systems.physics_plant)."""
