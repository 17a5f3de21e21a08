"""Topic and action names of the graph (one place, so nodes, CLI and recorder agree)."""

SCAN = "/afm/scan"  # afm_msgs/RasterScan, latched
SCAN_LINE = "/afm/scan_line"  # afm_msgs/ScanLine, sensor-data QoS
FORCE_TRACE = "/afm/force_trace"  # afm_msgs/ForceTrace, sensor-data QoS
TIP_COMMAND = "/afm/tip_command"  # afm_msgs/TipCommand
TIP_POSE = "/afm/tip_pose"  # geometry_msgs/PoseWithCovarianceStamped
GROUND_TRUTH = "/afm/ground_truth"  # afm_msgs/GroundTruth (sim only)
CORRECTED_MAP = "/afm/map"  # afm_msgs/RasterScan, drift-corrected, latched
LANDMARKS = "/afm/landmarks"  # afm_msgs/LandmarkArray, latched
TIP_SHAPE = "/afm/tip_shape"  # afm_msgs/TipShape, latched
PLANNED_PATH = "/afm/planned_path"  # afm_msgs/PlannedPath
PUSH_GOAL = "/afm/push_goal"  # geometry_msgs/PointStamped, every accepted push goal
MARKERS = "/afm/markers"  # visualization_msgs/MarkerArray
# afm_msgs/ObjectArray: objects as the push model predicts them per stroke (nano-hand, teleop)
# and as local scan lines observe them
OBJECTS_BELIEVED = "/afm/objects/believed"
# What viewers that know only standard messages show (Foxglove, RViz, rqt_image_view)
SCAN_IMAGE = "/afm/scan/image"  # sensor_msgs/Image rgb8, each scan colour-mapped, latched
MAP_IMAGE = "/afm/map/image"  # sensor_msgs/Image rgb8, each map colour-mapped, latched
LANDMARK_MARKERS = "/afm/landmarks/markers"  # visualization_msgs/MarkerArray, latched
TF = "/tf"  # tf2_msgs/TFMessage: afm_task -> afm_scanner as the localizer estimates it
TF_STATIC = "/tf_static"  # tf2_msgs/TFMessage, latched: the fixed part of the frame tree
# std_msgs/String, one JSON object per node, latched: the subscriptions each node's publishers
# have matched (afm_ros.links), so a client can wait until a recorder really hears a topic
LINKS = "/afm/links"

ACTION_SCAN_IMAGE = "/afm/scan_image"
ACTION_LOCAL_SCAN = "/afm/local_scan"
ACTION_MOVE_TIP = "/afm/move_tip"
ACTION_INDENT = "/afm/indent"
ACTION_LOCALIZE = "/afm/localize"
ACTION_PUSH_PARTICLE = "/afm/push_particle"
ACTION_ASSEMBLE = "/afm/assemble"
ACTION_SIM2REAL = "/afm/sim2real"
SERVICE_PLAN_PATH = "/afm/plan_path"
SERVICE_PLAN_OBSERVATION = "/afm/plan_observation"
SERVICE_PLAN_SEQUENCE = "/afm/plan_sequence"

# Teleoperation (afm_manipulation teleop, issue 33)
TELEOP_CMD_VEL = "/afm/teleop/cmd_vel"  # geometry_msgs/Twist, linear.x/.y m/s in afm_task
TELEOP_JOY = "/afm/teleop/joy"  # sensor_msgs/Joy (axes and buttons: the teleop node's params)
TELEOP_WRENCH = "/afm/teleop/wrench"  # geometry_msgs/WrenchStamped, N on the tip, afm_task
TELEOP_STATUS = "/afm/teleop/status"  # std_msgs/String, one JSON object, latched
SERVICE_TELEOP_ENABLE = "/afm/teleop/enable"  # std_srvs/SetBool: take (true) / hand back
SERVICE_TELEOP_CONTACT = "/afm/teleop/contact"  # std_srvs/SetBool: contact (true) / lifted
# served by the driver: std_srvs/SetBool, who holds the tip (true: teleop, false: automatic);
# teleop holds it on a lease it renews with a std_msgs/Empty on TELEOP_LEASE every
# TELEOP_LEASE_RENEW_S (a message renews, never grants: a late one after hand-back does nothing)
SERVICE_DRIVER_TELEOP = "/afm/driver/teleop"
TELEOP_LEASE = "/afm/teleop/lease"
TELEOP_LEASE_RENEW_S = 0.5
# served by the driver, MoveTip: the only goals it runs while teleop holds the tip
ACTION_TELEOP_MOVE_TIP = "/afm/teleop/move_tip"

RECORDED_BY_DEFAULT = [
    SCAN,
    SCAN_LINE,
    FORCE_TRACE,
    TIP_COMMAND,
    TIP_POSE,
    GROUND_TRUTH,
    CORRECTED_MAP,
    LANDMARKS,
    TIP_SHAPE,
    PLANNED_PATH,
    PUSH_GOAL,
    MARKERS,
    OBJECTS_BELIEVED,
    TELEOP_CMD_VEL,
    TELEOP_WRENCH,
    TELEOP_STATUS,
    SCAN_IMAGE,
    MAP_IMAGE,
    LANDMARK_MARKERS,
    TF,
    TF_STATIC,
]
