"""
Simulated piezo cantilever (plant) and excitation signals; ROS-free.

    from piezo_narx_ros.plant import PiezoCantilever, load_plant_params, generate
"""
from piezo_narx_ros.plant.params import PlantParams, load_plant_params
from piezo_narx_ros.plant.piezo import PiezoCantilever, PlantRun, adc_grid
from piezo_narx_ros.plant.session import random_history, session_offset
from piezo_narx_ros.plant.signals import (KINDS, OPTIONS, PREAMBLES, apply_limits, generate,
                                          preamble)

__all__ = ['PlantParams', 'load_plant_params', 'PiezoCantilever', 'PlantRun', 'generate',
           'apply_limits', 'KINDS', 'OPTIONS', 'PREAMBLES', 'preamble', 'adc_grid',
           'random_history', 'session_offset']
