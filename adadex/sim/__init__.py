"""MuJoCo layer: robot, objects, scene, batched simulator. Imports nothing from upper layers."""
