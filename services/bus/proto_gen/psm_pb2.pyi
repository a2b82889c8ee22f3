from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class Vec3(_message.Message):
    __slots__ = ("x", "y", "z")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class Quat(_message.Message):
    __slots__ = ("x", "y", "z", "w")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    W_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    w: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ..., w: _Optional[float] = ...) -> None: ...

class ArmState(_message.Message):
    __slots__ = ("stamp_ns", "tick", "sim_time_ns", "joint_names", "q", "dq", "ddq", "ee_position", "ee_orientation", "ee_linear_velocity", "ee_angular_velocity", "ee_linear_acceleration", "ee_angular_acceleration", "frame_id", "braking", "watchdog_tripped", "rejected_commands", "dt_s")
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    SIM_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    JOINT_NAMES_FIELD_NUMBER: _ClassVar[int]
    Q_FIELD_NUMBER: _ClassVar[int]
    DQ_FIELD_NUMBER: _ClassVar[int]
    DDQ_FIELD_NUMBER: _ClassVar[int]
    EE_POSITION_FIELD_NUMBER: _ClassVar[int]
    EE_ORIENTATION_FIELD_NUMBER: _ClassVar[int]
    EE_LINEAR_VELOCITY_FIELD_NUMBER: _ClassVar[int]
    EE_ANGULAR_VELOCITY_FIELD_NUMBER: _ClassVar[int]
    EE_LINEAR_ACCELERATION_FIELD_NUMBER: _ClassVar[int]
    EE_ANGULAR_ACCELERATION_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    BRAKING_FIELD_NUMBER: _ClassVar[int]
    WATCHDOG_TRIPPED_FIELD_NUMBER: _ClassVar[int]
    REJECTED_COMMANDS_FIELD_NUMBER: _ClassVar[int]
    DT_S_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    tick: int
    sim_time_ns: int
    joint_names: _containers.RepeatedScalarFieldContainer[str]
    q: _containers.RepeatedScalarFieldContainer[float]
    dq: _containers.RepeatedScalarFieldContainer[float]
    ddq: _containers.RepeatedScalarFieldContainer[float]
    ee_position: Vec3
    ee_orientation: Quat
    ee_linear_velocity: Vec3
    ee_angular_velocity: Vec3
    ee_linear_acceleration: Vec3
    ee_angular_acceleration: Vec3
    frame_id: str
    braking: bool
    watchdog_tripped: bool
    rejected_commands: int
    dt_s: float
    def __init__(self, stamp_ns: _Optional[int] = ..., tick: _Optional[int] = ..., sim_time_ns: _Optional[int] = ..., joint_names: _Optional[_Iterable[str]] = ..., q: _Optional[_Iterable[float]] = ..., dq: _Optional[_Iterable[float]] = ..., ddq: _Optional[_Iterable[float]] = ..., ee_position: _Optional[_Union[Vec3, _Mapping]] = ..., ee_orientation: _Optional[_Union[Quat, _Mapping]] = ..., ee_linear_velocity: _Optional[_Union[Vec3, _Mapping]] = ..., ee_angular_velocity: _Optional[_Union[Vec3, _Mapping]] = ..., ee_linear_acceleration: _Optional[_Union[Vec3, _Mapping]] = ..., ee_angular_acceleration: _Optional[_Union[Vec3, _Mapping]] = ..., frame_id: _Optional[str] = ..., braking: _Optional[bool] = ..., watchdog_tripped: _Optional[bool] = ..., rejected_commands: _Optional[int] = ..., dt_s: _Optional[float] = ...) -> None: ...

class ArmCommand(_message.Message):
    __slots__ = ("stamp_ns", "seq", "tick", "mode", "linear_acceleration", "orientation_reference", "angular_velocity_reference", "has_angular_velocity_reference", "joint_accelerations", "source", "frame_id", "goal_updates")
    class Mode(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        MODE_UNSPECIFIED: _ClassVar[ArmCommand.Mode]
        CARTESIAN_ACCELERATION: _ClassVar[ArmCommand.Mode]
        JOINT_ACCELERATION: _ClassVar[ArmCommand.Mode]
    MODE_UNSPECIFIED: ArmCommand.Mode
    CARTESIAN_ACCELERATION: ArmCommand.Mode
    JOINT_ACCELERATION: ArmCommand.Mode
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    LINEAR_ACCELERATION_FIELD_NUMBER: _ClassVar[int]
    ORIENTATION_REFERENCE_FIELD_NUMBER: _ClassVar[int]
    ANGULAR_VELOCITY_REFERENCE_FIELD_NUMBER: _ClassVar[int]
    HAS_ANGULAR_VELOCITY_REFERENCE_FIELD_NUMBER: _ClassVar[int]
    JOINT_ACCELERATIONS_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    GOAL_UPDATES_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    seq: int
    tick: int
    mode: ArmCommand.Mode
    linear_acceleration: Vec3
    orientation_reference: Quat
    angular_velocity_reference: Vec3
    has_angular_velocity_reference: bool
    joint_accelerations: _containers.RepeatedScalarFieldContainer[float]
    source: str
    frame_id: str
    goal_updates: _containers.RepeatedCompositeFieldContainer[GoalUpdateRef]
    def __init__(self, stamp_ns: _Optional[int] = ..., seq: _Optional[int] = ..., tick: _Optional[int] = ..., mode: _Optional[_Union[ArmCommand.Mode, str]] = ..., linear_acceleration: _Optional[_Union[Vec3, _Mapping]] = ..., orientation_reference: _Optional[_Union[Quat, _Mapping]] = ..., angular_velocity_reference: _Optional[_Union[Vec3, _Mapping]] = ..., has_angular_velocity_reference: _Optional[bool] = ..., joint_accelerations: _Optional[_Iterable[float]] = ..., source: _Optional[str] = ..., frame_id: _Optional[str] = ..., goal_updates: _Optional[_Iterable[_Union[GoalUpdateRef, _Mapping]]] = ...) -> None: ...

class GoalUpdateRef(_message.Message):
    __slots__ = ("name", "stamp_ns")
    NAME_FIELD_NUMBER: _ClassVar[int]
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    name: str
    stamp_ns: int
    def __init__(self, name: _Optional[str] = ..., stamp_ns: _Optional[int] = ...) -> None: ...

class Goal(_message.Message):
    __slots__ = ("stamp_ns", "seq", "name", "position", "covariance", "valid", "invalid_reason", "source", "frame_stamp_ns", "frame_id", "velocity")
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    NAME_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    COVARIANCE_FIELD_NUMBER: _ClassVar[int]
    VALID_FIELD_NUMBER: _ClassVar[int]
    INVALID_REASON_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    FRAME_STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    VELOCITY_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    seq: int
    name: str
    position: Vec3
    covariance: _containers.RepeatedScalarFieldContainer[float]
    valid: bool
    invalid_reason: str
    source: str
    frame_stamp_ns: int
    frame_id: str
    velocity: Vec3
    def __init__(self, stamp_ns: _Optional[int] = ..., seq: _Optional[int] = ..., name: _Optional[str] = ..., position: _Optional[_Union[Vec3, _Mapping]] = ..., covariance: _Optional[_Iterable[float]] = ..., valid: _Optional[bool] = ..., invalid_reason: _Optional[str] = ..., source: _Optional[str] = ..., frame_stamp_ns: _Optional[int] = ..., frame_id: _Optional[str] = ..., velocity: _Optional[_Union[Vec3, _Mapping]] = ...) -> None: ...

class FaceBox(_message.Message):
    __slots__ = ("x_px", "y_px", "w_px", "h_px", "confidence")
    X_PX_FIELD_NUMBER: _ClassVar[int]
    Y_PX_FIELD_NUMBER: _ClassVar[int]
    W_PX_FIELD_NUMBER: _ClassVar[int]
    H_PX_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    x_px: float
    y_px: float
    w_px: float
    h_px: float
    confidence: float
    def __init__(self, x_px: _Optional[float] = ..., y_px: _Optional[float] = ..., w_px: _Optional[float] = ..., h_px: _Optional[float] = ..., confidence: _Optional[float] = ...) -> None: ...

class FaceDetections(_message.Message):
    __slots__ = ("stamp_ns", "seq", "frame_stamp_ns", "camera_id", "image_width", "image_height", "boxes", "target_index")
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    FRAME_STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    CAMERA_ID_FIELD_NUMBER: _ClassVar[int]
    IMAGE_WIDTH_FIELD_NUMBER: _ClassVar[int]
    IMAGE_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    BOXES_FIELD_NUMBER: _ClassVar[int]
    TARGET_INDEX_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    seq: int
    frame_stamp_ns: int
    camera_id: str
    image_width: int
    image_height: int
    boxes: _containers.RepeatedCompositeFieldContainer[FaceBox]
    target_index: int
    def __init__(self, stamp_ns: _Optional[int] = ..., seq: _Optional[int] = ..., frame_stamp_ns: _Optional[int] = ..., camera_id: _Optional[str] = ..., image_width: _Optional[int] = ..., image_height: _Optional[int] = ..., boxes: _Optional[_Iterable[_Union[FaceBox, _Mapping]]] = ..., target_index: _Optional[int] = ...) -> None: ...

class Obstacle(_message.Message):
    __slots__ = ("id", "shape", "position", "orientation", "size", "velocity")
    class Shape(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        SHAPE_UNSPECIFIED: _ClassVar[Obstacle.Shape]
        BOX: _ClassVar[Obstacle.Shape]
        SPHERE: _ClassVar[Obstacle.Shape]
        CYLINDER: _ClassVar[Obstacle.Shape]
    SHAPE_UNSPECIFIED: Obstacle.Shape
    BOX: Obstacle.Shape
    SPHERE: Obstacle.Shape
    CYLINDER: Obstacle.Shape
    ID_FIELD_NUMBER: _ClassVar[int]
    SHAPE_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    ORIENTATION_FIELD_NUMBER: _ClassVar[int]
    SIZE_FIELD_NUMBER: _ClassVar[int]
    VELOCITY_FIELD_NUMBER: _ClassVar[int]
    id: str
    shape: Obstacle.Shape
    position: Vec3
    orientation: Quat
    size: Vec3
    velocity: Vec3
    def __init__(self, id: _Optional[str] = ..., shape: _Optional[_Union[Obstacle.Shape, str]] = ..., position: _Optional[_Union[Vec3, _Mapping]] = ..., orientation: _Optional[_Union[Quat, _Mapping]] = ..., size: _Optional[_Union[Vec3, _Mapping]] = ..., velocity: _Optional[_Union[Vec3, _Mapping]] = ...) -> None: ...

class ObstacleSet(_message.Message):
    __slots__ = ("stamp_ns", "seq", "frame_id", "obstacles")
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    FRAME_ID_FIELD_NUMBER: _ClassVar[int]
    OBSTACLES_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    seq: int
    frame_id: str
    obstacles: _containers.RepeatedCompositeFieldContainer[Obstacle]
    def __init__(self, stamp_ns: _Optional[int] = ..., seq: _Optional[int] = ..., frame_id: _Optional[str] = ..., obstacles: _Optional[_Iterable[_Union[Obstacle, _Mapping]]] = ...) -> None: ...

class CollisionPrediction(_message.Message):
    __slots__ = ("stamp_ns", "seq", "collision", "obstacle_id", "stop_position", "time_to_collision_s", "state_tick", "goal", "goal_known", "inside", "entry_point", "entry_distance_m", "min_clearance_m", "closest_link", "clearance_obstacle_id", "clearance_tick", "protective_stop", "detail", "obstacle_count")
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    COLLISION_FIELD_NUMBER: _ClassVar[int]
    OBSTACLE_ID_FIELD_NUMBER: _ClassVar[int]
    STOP_POSITION_FIELD_NUMBER: _ClassVar[int]
    TIME_TO_COLLISION_S_FIELD_NUMBER: _ClassVar[int]
    STATE_TICK_FIELD_NUMBER: _ClassVar[int]
    GOAL_FIELD_NUMBER: _ClassVar[int]
    GOAL_KNOWN_FIELD_NUMBER: _ClassVar[int]
    INSIDE_FIELD_NUMBER: _ClassVar[int]
    ENTRY_POINT_FIELD_NUMBER: _ClassVar[int]
    ENTRY_DISTANCE_M_FIELD_NUMBER: _ClassVar[int]
    MIN_CLEARANCE_M_FIELD_NUMBER: _ClassVar[int]
    CLOSEST_LINK_FIELD_NUMBER: _ClassVar[int]
    CLEARANCE_OBSTACLE_ID_FIELD_NUMBER: _ClassVar[int]
    CLEARANCE_TICK_FIELD_NUMBER: _ClassVar[int]
    PROTECTIVE_STOP_FIELD_NUMBER: _ClassVar[int]
    DETAIL_FIELD_NUMBER: _ClassVar[int]
    OBSTACLE_COUNT_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    seq: int
    collision: bool
    obstacle_id: str
    stop_position: _containers.RepeatedScalarFieldContainer[float]
    time_to_collision_s: float
    state_tick: int
    goal: Vec3
    goal_known: bool
    inside: bool
    entry_point: Vec3
    entry_distance_m: float
    min_clearance_m: float
    closest_link: str
    clearance_obstacle_id: str
    clearance_tick: int
    protective_stop: bool
    detail: str
    obstacle_count: int
    def __init__(self, stamp_ns: _Optional[int] = ..., seq: _Optional[int] = ..., collision: _Optional[bool] = ..., obstacle_id: _Optional[str] = ..., stop_position: _Optional[_Iterable[float]] = ..., time_to_collision_s: _Optional[float] = ..., state_tick: _Optional[int] = ..., goal: _Optional[_Union[Vec3, _Mapping]] = ..., goal_known: _Optional[bool] = ..., inside: _Optional[bool] = ..., entry_point: _Optional[_Union[Vec3, _Mapping]] = ..., entry_distance_m: _Optional[float] = ..., min_clearance_m: _Optional[float] = ..., closest_link: _Optional[str] = ..., clearance_obstacle_id: _Optional[str] = ..., clearance_tick: _Optional[int] = ..., protective_stop: _Optional[bool] = ..., detail: _Optional[str] = ..., obstacle_count: _Optional[int] = ...) -> None: ...

class ObstacleCommand(_message.Message):
    __slots__ = ("stamp_ns", "seq", "action", "obstacle", "id", "source")
    class Action(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        ACTION_UNSPECIFIED: _ClassVar[ObstacleCommand.Action]
        ADD: _ClassVar[ObstacleCommand.Action]
        MOVE: _ClassVar[ObstacleCommand.Action]
        REMOVE: _ClassVar[ObstacleCommand.Action]
        CLEAR: _ClassVar[ObstacleCommand.Action]
    ACTION_UNSPECIFIED: ObstacleCommand.Action
    ADD: ObstacleCommand.Action
    MOVE: ObstacleCommand.Action
    REMOVE: ObstacleCommand.Action
    CLEAR: ObstacleCommand.Action
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    OBSTACLE_FIELD_NUMBER: _ClassVar[int]
    ID_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    seq: int
    action: ObstacleCommand.Action
    obstacle: Obstacle
    id: str
    source: str
    def __init__(self, stamp_ns: _Optional[int] = ..., seq: _Optional[int] = ..., action: _Optional[_Union[ObstacleCommand.Action, str]] = ..., obstacle: _Optional[_Union[Obstacle, _Mapping]] = ..., id: _Optional[str] = ..., source: _Optional[str] = ...) -> None: ...

class PlannerStatus(_message.Message):
    __slots__ = ("stamp_ns", "seq", "state", "task", "segment_index", "time_to_go_s", "goal", "goal_name", "state_tick", "detail", "step", "step_index", "step_count", "mode", "distance_to_goal_m", "speed_mps", "orientation_reference", "latency_p50_us", "latency_p99_us", "latency_max_us", "answered", "rejected_states", "rejected_goals", "step_elapsed_s", "goal_speed_mps", "collision_check", "collision", "obstacle_id", "stop_position", "min_clearance_m", "prediction_age_s", "monitor_alive", "collision_stops", "waited_states")
    class State(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        STATE_UNSPECIFIED: _ClassVar[PlannerStatus.State]
        IDLE: _ClassVar[PlannerStatus.State]
        RUNNING: _ClassVar[PlannerStatus.State]
        HOLDING: _ClassVar[PlannerStatus.State]
        DONE: _ClassVar[PlannerStatus.State]
        FAULT: _ClassVar[PlannerStatus.State]
    STATE_UNSPECIFIED: PlannerStatus.State
    IDLE: PlannerStatus.State
    RUNNING: PlannerStatus.State
    HOLDING: PlannerStatus.State
    DONE: PlannerStatus.State
    FAULT: PlannerStatus.State
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    TASK_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_INDEX_FIELD_NUMBER: _ClassVar[int]
    TIME_TO_GO_S_FIELD_NUMBER: _ClassVar[int]
    GOAL_FIELD_NUMBER: _ClassVar[int]
    GOAL_NAME_FIELD_NUMBER: _ClassVar[int]
    STATE_TICK_FIELD_NUMBER: _ClassVar[int]
    DETAIL_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    STEP_INDEX_FIELD_NUMBER: _ClassVar[int]
    STEP_COUNT_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_TO_GOAL_M_FIELD_NUMBER: _ClassVar[int]
    SPEED_MPS_FIELD_NUMBER: _ClassVar[int]
    ORIENTATION_REFERENCE_FIELD_NUMBER: _ClassVar[int]
    LATENCY_P50_US_FIELD_NUMBER: _ClassVar[int]
    LATENCY_P99_US_FIELD_NUMBER: _ClassVar[int]
    LATENCY_MAX_US_FIELD_NUMBER: _ClassVar[int]
    ANSWERED_FIELD_NUMBER: _ClassVar[int]
    REJECTED_STATES_FIELD_NUMBER: _ClassVar[int]
    REJECTED_GOALS_FIELD_NUMBER: _ClassVar[int]
    STEP_ELAPSED_S_FIELD_NUMBER: _ClassVar[int]
    GOAL_SPEED_MPS_FIELD_NUMBER: _ClassVar[int]
    COLLISION_CHECK_FIELD_NUMBER: _ClassVar[int]
    COLLISION_FIELD_NUMBER: _ClassVar[int]
    OBSTACLE_ID_FIELD_NUMBER: _ClassVar[int]
    STOP_POSITION_FIELD_NUMBER: _ClassVar[int]
    MIN_CLEARANCE_M_FIELD_NUMBER: _ClassVar[int]
    PREDICTION_AGE_S_FIELD_NUMBER: _ClassVar[int]
    MONITOR_ALIVE_FIELD_NUMBER: _ClassVar[int]
    COLLISION_STOPS_FIELD_NUMBER: _ClassVar[int]
    WAITED_STATES_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    seq: int
    state: PlannerStatus.State
    task: str
    segment_index: _containers.RepeatedScalarFieldContainer[int]
    time_to_go_s: _containers.RepeatedScalarFieldContainer[float]
    goal: Vec3
    goal_name: str
    state_tick: int
    detail: str
    step: str
    step_index: int
    step_count: int
    mode: _containers.RepeatedScalarFieldContainer[str]
    distance_to_goal_m: float
    speed_mps: float
    orientation_reference: Quat
    latency_p50_us: float
    latency_p99_us: float
    latency_max_us: float
    answered: int
    rejected_states: int
    rejected_goals: int
    step_elapsed_s: float
    goal_speed_mps: float
    collision_check: bool
    collision: bool
    obstacle_id: str
    stop_position: _containers.RepeatedScalarFieldContainer[float]
    min_clearance_m: float
    prediction_age_s: float
    monitor_alive: bool
    collision_stops: int
    waited_states: int
    def __init__(self, stamp_ns: _Optional[int] = ..., seq: _Optional[int] = ..., state: _Optional[_Union[PlannerStatus.State, str]] = ..., task: _Optional[str] = ..., segment_index: _Optional[_Iterable[int]] = ..., time_to_go_s: _Optional[_Iterable[float]] = ..., goal: _Optional[_Union[Vec3, _Mapping]] = ..., goal_name: _Optional[str] = ..., state_tick: _Optional[int] = ..., detail: _Optional[str] = ..., step: _Optional[str] = ..., step_index: _Optional[int] = ..., step_count: _Optional[int] = ..., mode: _Optional[_Iterable[str]] = ..., distance_to_goal_m: _Optional[float] = ..., speed_mps: _Optional[float] = ..., orientation_reference: _Optional[_Union[Quat, _Mapping]] = ..., latency_p50_us: _Optional[float] = ..., latency_p99_us: _Optional[float] = ..., latency_max_us: _Optional[float] = ..., answered: _Optional[int] = ..., rejected_states: _Optional[int] = ..., rejected_goals: _Optional[int] = ..., step_elapsed_s: _Optional[float] = ..., goal_speed_mps: _Optional[float] = ..., collision_check: _Optional[bool] = ..., collision: _Optional[bool] = ..., obstacle_id: _Optional[str] = ..., stop_position: _Optional[_Iterable[float]] = ..., min_clearance_m: _Optional[float] = ..., prediction_age_s: _Optional[float] = ..., monitor_alive: _Optional[bool] = ..., collision_stops: _Optional[int] = ..., waited_states: _Optional[int] = ...) -> None: ...

class TaskEvent(_message.Message):
    __slots__ = ("stamp_ns", "seq", "task", "kind", "detail", "step", "step_index", "state_tick", "summary_json")
    class Kind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        KIND_UNSPECIFIED: _ClassVar[TaskEvent.Kind]
        STARTED: _ClassVar[TaskEvent.Kind]
        SEGMENT_CHANGED: _ClassVar[TaskEvent.Kind]
        GOAL_CHANGED: _ClassVar[TaskEvent.Kind]
        GOAL_LOST: _ClassVar[TaskEvent.Kind]
        PAUSED: _ClassVar[TaskEvent.Kind]
        RESUMED: _ClassVar[TaskEvent.Kind]
        COMPLETED: _ClassVar[TaskEvent.Kind]
        ABORTED: _ClassVar[TaskEvent.Kind]
        ERROR: _ClassVar[TaskEvent.Kind]
        GRIPPER: _ClassVar[TaskEvent.Kind]
        STEP_COMPLETED: _ClassVar[TaskEvent.Kind]
        COLLISION_PREDICTED: _ClassVar[TaskEvent.Kind]
        PATH_CLEAR: _ClassVar[TaskEvent.Kind]
    KIND_UNSPECIFIED: TaskEvent.Kind
    STARTED: TaskEvent.Kind
    SEGMENT_CHANGED: TaskEvent.Kind
    GOAL_CHANGED: TaskEvent.Kind
    GOAL_LOST: TaskEvent.Kind
    PAUSED: TaskEvent.Kind
    RESUMED: TaskEvent.Kind
    COMPLETED: TaskEvent.Kind
    ABORTED: TaskEvent.Kind
    ERROR: TaskEvent.Kind
    GRIPPER: TaskEvent.Kind
    STEP_COMPLETED: TaskEvent.Kind
    COLLISION_PREDICTED: TaskEvent.Kind
    PATH_CLEAR: TaskEvent.Kind
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    TASK_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    DETAIL_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    STEP_INDEX_FIELD_NUMBER: _ClassVar[int]
    STATE_TICK_FIELD_NUMBER: _ClassVar[int]
    SUMMARY_JSON_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    seq: int
    task: str
    kind: TaskEvent.Kind
    detail: str
    step: str
    step_index: int
    state_tick: int
    summary_json: str
    def __init__(self, stamp_ns: _Optional[int] = ..., seq: _Optional[int] = ..., task: _Optional[str] = ..., kind: _Optional[_Union[TaskEvent.Kind, str]] = ..., detail: _Optional[str] = ..., step: _Optional[str] = ..., step_index: _Optional[int] = ..., state_tick: _Optional[int] = ..., summary_json: _Optional[str] = ...) -> None: ...

class GripperCommand(_message.Message):
    __slots__ = ("stamp_ns", "seq", "action", "step", "source")
    class Action(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        ACTION_UNSPECIFIED: _ClassVar[GripperCommand.Action]
        OPEN: _ClassVar[GripperCommand.Action]
        CLOSE: _ClassVar[GripperCommand.Action]
    ACTION_UNSPECIFIED: GripperCommand.Action
    OPEN: GripperCommand.Action
    CLOSE: GripperCommand.Action
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    seq: int
    action: GripperCommand.Action
    step: str
    source: str
    def __init__(self, stamp_ns: _Optional[int] = ..., seq: _Optional[int] = ..., action: _Optional[_Union[GripperCommand.Action, str]] = ..., step: _Optional[str] = ..., source: _Optional[str] = ...) -> None: ...

class ServiceStatus(_message.Message):
    __slots__ = ("stamp_ns", "seq", "service", "state", "received", "rejected", "published", "errors", "dropped", "uptime_s", "last_error", "version", "queued", "rejected_by_reason")
    class State(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
        __slots__ = ()
        STATE_UNSPECIFIED: _ClassVar[ServiceStatus.State]
        STARTING: _ClassVar[ServiceStatus.State]
        RUNNING: _ClassVar[ServiceStatus.State]
        DEGRADED: _ClassVar[ServiceStatus.State]
        STOPPING: _ClassVar[ServiceStatus.State]
    STATE_UNSPECIFIED: ServiceStatus.State
    STARTING: ServiceStatus.State
    RUNNING: ServiceStatus.State
    DEGRADED: ServiceStatus.State
    STOPPING: ServiceStatus.State
    class RejectedByReasonEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    STAMP_NS_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    SERVICE_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    RECEIVED_FIELD_NUMBER: _ClassVar[int]
    REJECTED_FIELD_NUMBER: _ClassVar[int]
    PUBLISHED_FIELD_NUMBER: _ClassVar[int]
    ERRORS_FIELD_NUMBER: _ClassVar[int]
    DROPPED_FIELD_NUMBER: _ClassVar[int]
    UPTIME_S_FIELD_NUMBER: _ClassVar[int]
    LAST_ERROR_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    QUEUED_FIELD_NUMBER: _ClassVar[int]
    REJECTED_BY_REASON_FIELD_NUMBER: _ClassVar[int]
    stamp_ns: int
    seq: int
    service: str
    state: ServiceStatus.State
    received: int
    rejected: int
    published: int
    errors: int
    dropped: int
    uptime_s: float
    last_error: str
    version: str
    queued: int
    rejected_by_reason: _containers.ScalarMap[str, int]
    def __init__(self, stamp_ns: _Optional[int] = ..., seq: _Optional[int] = ..., service: _Optional[str] = ..., state: _Optional[_Union[ServiceStatus.State, str]] = ..., received: _Optional[int] = ..., rejected: _Optional[int] = ..., published: _Optional[int] = ..., errors: _Optional[int] = ..., dropped: _Optional[int] = ..., uptime_s: _Optional[float] = ..., last_error: _Optional[str] = ..., version: _Optional[str] = ..., queued: _Optional[int] = ..., rejected_by_reason: _Optional[_Mapping[str, int]] = ...) -> None: ...
