"""
piezo_narx_ros: NARX identification of piezo hysteresis and a ROS 2 free-run deflection estimator.

Subpackages, one per concern:
    ident      identification core (ROS-free): regressors, NARX network, ARX, training, metrics,
               Billings correlation tests, the paper's experiment, model files, report figures
    plant      piezo cantilever plant model and excitation signals (ROS-free)
    estimator  online free-run estimator logic used by the estimator node (ROS-free)
    command    sample clock and command streaming logic used by the command node (ROS-free)
    rig        real-rig driver logic: UDP datagrams, limits, watchdog, and a fake rig (ROS-free)
    bag        rosbag2 MCAP record/read/repair and u/y pairing (ROS-free)
    nodes      thin rclpy nodes, one per file
    cli        the `piezo-narx` command line
"""
__version__ = '0.1.0'
