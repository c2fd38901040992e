"""The configuration tree of a mission: one nested dataclass, the CLI is generated from it.

Field docstrings are the ``--help`` text. Units are part of field names. ``rovergate run``
saves the resolved tree as ``config.json`` beside the run's outputs, and every module process
of the run loads that same file (``--config``).
"""

from __future__ import annotations

import dataclasses
import json
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import tyro

from rovergate.errors import ConfigError
from rovergate.platforms import Platform, get_platform


@dataclass
class SessionConfig:
    """How a process joins the Zenoh network."""

    mode: Literal["peer", "client", "router"] = "peer"
    """Zenoh mode of this process."""
    connect: tuple[str, ...] = ()
    """Endpoints to connect to, e.g. tcp/127.0.0.1:7447."""
    listen: tuple[str, ...] = ()
    """Endpoints to listen on, e.g. tcp/0.0.0.0:7447 to let other machines connect (to
    `rovergate run`: read-only for them, see rovergate/access.py)."""
    namespace: str = "rover"
    """Prefix of every key expression, so that several rovers can share one network."""
    multicast_scouting: bool = False
    """Discover peers by UDP multicast. Off by default: endpoints are explicit."""
    wait_for_peers: int = 0
    """Before declaring itself ready, wait until this many peers are linked (`rovergate run`
    starts its modules as clients with 1: linked to the mission's session)."""
    keyframe_every: int = 25
    """The incremental maps (S_t, the prediction, the planner map) travel as what changed, and
    whole at a multiple of this many steps once the changes since the last whole map add up
    to its size (rovergate/streams.py): a subscriber that joins late waits that long for the
    whole map (25 steps in a 30 m box; a long traverse's map, hundreds of steps)."""


@dataclass
class SceneConfig:
    """Which world to map."""

    name: str = "arch_field"
    """A suite scene (`rovergate scenes` lists them) or the path of a mesh file that trimesh
    reads (OBJ, PLY, STL, GLB). `--scene X` is short for `--scene.name X`."""
    up_axis: str = "z"
    """Mesh scenes: the file's up axis (x, y, z, -x, -y or -z); it becomes +z."""
    scale: float = 1.0
    """Mesh scenes: metres per file unit."""
    region_m: float = 40.0
    """Mesh scenes: the default box of interest is the mesh's footprint, cut to a square of at
    most this side around its centre (a rover's working area)."""
    d_scene_m: float = 0.0
    """Diagonal of the scene's box of interest. 0: take it from the scene (recommended)."""
    bounds_m: tuple[float, float, float, float, float, float] = (0, 0, 0, 0, 0, 0)
    """Box of interest (xmin, ymin, zmin, xmax, ymax, zmax). Zeros: take it from the scene."""

    @property
    def resolved(self) -> bool:
        return self.d_scene_m > 0 and any(self.bounds_m)


@dataclass
class SensorConfig:
    """The depth camera on the rover's pan-tilt mast."""

    width_px: int = 160
    """Image width in pixels."""
    height_px: int = 120
    """Image height in pixels."""
    vfov_deg: float = 45.0
    """Vertical field of view (the horizontal one follows from the aspect ratio)."""
    min_range_m: float = 0.3
    """Returns nearer than this are dropped (NaN)."""
    max_range_m: float = 20.0
    """Returns farther than this are dropped (NaN); also the far plane of frustums."""
    mast_height_m: float = 1.6
    """Height of the camera above the ground under the rover's centre."""
    mast_forward_m: float = 0.3
    """Forward offset of the mast from the rover's centre."""
    pan_deg: float = 0.0
    """Mast pan, positive to the left."""
    tilt_deg: float = -15.0
    """Mast tilt, negative looks down."""


@dataclass
class RoverConfig:
    """The rover body, as the simulator and the planner's collision checks see it."""

    length_m: float = 1.0
    """Body length."""
    width_m: float = 0.7
    """Body width."""
    clearance_m: float = 0.25
    """Ground clearance: what is lower than this over the ground passes under the body."""
    body_top_m: float = 0.9
    """Top of the body above the ground (the mast above it is thin and is not checked)."""
    check_spacing_m: float = 0.05
    """Spacing of collision checks along an executed motion."""
    slope_limit_deg: float = 25.0
    """Steepest ground the rover drives on (roll or pitch of the plane under its wheels)."""
    step_limit_m: float = 0.2
    """Highest step under the body: the ground may depart this far from the wheels' plane."""
    look_around: bool = True
    """A rover that did not move in a step pans its mast to look around: the next frame looks
    90 degrees left, then right, then behind (one a step, for as long as it stays put), and
    the mast faces forward again once it drives. A turn in place looks around too; this is
    the look where no turn is free."""


@dataclass
class HazcamConfig:
    """The rover's body-mounted hazard cameras: one at the front of the body looking ahead
    and down, one at the back looking behind and down (as Perseverance's four hazcams, here
    one depth camera at each end). They see the ground the mast camera cannot: from the
    body's edge out to a few metres. Optical frames ``hazcam_front_optical`` and
    ``hazcam_rear_optical``; mounted ``forward_m`` ahead of (behind) the rover's centre,
    ``height_m`` above the ground under it, ``tilt_deg`` down."""

    enabled: bool = True
    """Render and publish them (rover only; the flyer has none, and publishes empty images)."""
    width_px: int = 128
    """Image width in pixels."""
    height_px: int = 96
    """Image height in pixels."""
    vfov_deg: float = 90.0
    """Vertical field of view (horizontal: 106 degrees at 128 x 96)."""
    min_range_m: float = 0.2
    """Returns nearer than this are dropped (NaN)."""
    max_range_m: float = 5.0
    """Returns farther than this are dropped; the ground a hazard camera sees ends here."""
    height_m: float = 0.8
    """Height of each camera above the ground under the rover's centre."""
    forward_m: float = 0.5
    """Distance of each camera ahead of (front) or behind (rear) the rover's centre."""
    tilt_deg: float = -45.0
    """Tilt below the horizon; with the 90-degree field, the lowest rows look straight down."""
    feed_map: bool = True
    """Also integrate their frames into the observed surface S_t and the learned model's
    occupancy grid (so into coverage and the model's input). Off (``--hazcam.no-feed-map``):
    they feed the traversability layer only, as the paper's single-camera setting has it; on
    the stuck starts of issue 26 the learned map then walls the rover in
    (docs/platforms.md, "Driving").
    The gate's exposure counts and the points' views stay the mast camera's either way."""


@dataclass
class TraverseConfig:
    """The rover's traversability layer (planner/traversability.py): a 2.5D height map from
    observed returns only, and an ACE-like check of every motion the rover drives."""

    enabled: bool = True
    """Check motions on it (off: the map's own ground estimate alone, as before issue 26)."""
    cell_m: float = 0.1
    """Cell of the height map."""
    mast_range_m: float = 8.0
    """Mast returns farther than this are not used (sparse along the ground, and no motion of
    one step reaches that far)."""
    max_roll_deg: float = 20.0
    """Steepest side slope the rover drives (roll of the plane through its wheels)."""
    max_pitch_deg: float = 25.0
    """Steepest slope along its heading (pitch of that plane)."""
    wheel_drop_m: float = 0.18
    """Largest drop or rise under a wheel: the ground in a wheel's patch may span this much,
    and the wheels may depart this far from their plane."""
    belly_margin_m: float = 0.07
    """Nothing under the body may stand higher over the wheels' plane than the body's ground
    clearance less this (0.25 - 0.07 = 0.18 m)."""
    side_margin_m: float = 0.1
    """The footprint checked is the body widened by this on every side."""
    backout_steps: int = 6
    """How many past poses a rover with no forward motion may back out along."""
    dither_window: int = 5
    """A step ends a dither when the rover stands within ``dither_min_m`` of where it stood
    this many steps before: its motions have gone nowhere (greedy view selection pulled back
    and forth by the same gain)."""
    dither_min_m: float = 1.0
    """See ``dither_window``."""
    dither_radius_m: float = 1.5
    """Candidates within this of where a dither ended, over the last ``dither_memory`` steps,
    are tried after all the others."""
    dither_memory: int = 30
    """How many steps a dither's spot is remembered."""
    revisit_steps: int = 10
    """Candidates within ``revisit_m`` of where the rover stood at one of this many steps
    before the current one are tried after the others (before those near a dither's spot):
    greedy view selection otherwise drives out and back to the same spot (0: off)."""
    revisit_m: float = 1.0
    """See ``revisit_steps``."""


@dataclass
class FlyerConfig:
    """The free-flying camera (the paper's benchmark platform): a sphere with a camera."""

    radius_m: float = 0.3
    """Radius of the sphere that must stay clear of the scene."""
    altitude_m: float = 1.6
    """Height above the ground of the flyer's starts."""
    min_altitude_m: float = 0.5
    """Lowest height above the ground the planner flies at."""
    max_altitude_m: float = 6.0
    """Highest height above the ground the planner flies at."""
    min_pitch_deg: float = -60.0
    """Lowest view direction (negative looks down)."""
    max_pitch_deg: float = 20.0
    """Highest view direction."""


@dataclass
class SensingConfig:
    """Degraded sensing (the paper's untested conditions, its Table 3). All off by default;
    every draw is seeded from the mission seed and the step."""

    noise_frac: float = 0.0
    """Depth noise: standard deviation as a fraction of the range (0.01: 1 cm at 1 m)."""
    dropout_pixel_prob: float = 0.0
    """Independent missing returns: probability that a pixel has none."""
    dropout_blob_frac: float = 0.0
    """Structured missing returns: the share of each image lost in blobs."""
    dropout_blob_px: float = 4.0
    """Blob size: the smoothing scale, in pixels, of the field the blobs are cut from."""
    grazing_max_deg: float = 90.0
    """Returns from surfaces seen at an incidence angle above this are lost (90: off)."""
    drift_xy_m: float = 0.0
    """Pose drift: standard deviation per step of the random walk in x and y."""
    drift_z_m: float = 0.0
    """Pose drift: standard deviation per step of the random walk in z."""
    drift_yaw_deg: float = 0.0
    """Pose drift: standard deviation per step of the random walk in heading."""

    @property
    def drifts(self) -> bool:
        return self.drift_xy_m > 0 or self.drift_z_m > 0 or self.drift_yaw_deg > 0


@dataclass
class MapperConfig:
    """Integration of depth into the observed surface S_t."""

    voxel_m: float = 0.15
    """Voxel edge of the observed surface: one point is kept per voxel."""
    prediction: str = "auto"
    """Run the learned occupancy model: auto (when the condition uses it), on, or off."""
    checkpoint: str = ""
    """Occupancy model weights. Empty: the checkpoint shipped in the package."""
    precision: str = "float32"
    """The model's arithmetic: float32 (the trained model's own; the same on every CPU as far
    as the CPU's kernels allow, see docs/learned-model.md) or bfloat16 (faster only on a CPU with
    native bfloat16, AVX512-BF16 or AMX; about one covered voxel in 13,000 lands on the other side
    of 0.5; many times slower in torch without native support, and refused by openvino)."""
    engine: str = "openvino"
    """The runtime of the model's pass: openvino (the network compiled for this CPU, 1.8 to 2
    times faster than torch with one thread, with AVX-512 or AVX2) or torch (the network as
    trained, in PyTorch)."""


@dataclass
class GateConfig:
    """The observation-gated filter (paper, equation 4)."""

    k: int = 2
    """Frustum inclusions after which an unsupported prediction is suppressed."""
    epsilon_frac: float = 0.03
    """Support radius as a fraction of d_scene (paper: 0.03)."""
    oracle_delta_frac: float = 0.03
    """Oracle tagging tolerance as a fraction of d_scene (paper: 0.03)."""
    view_tolerance_m: float = 0.3
    """A frame saw a map point when its return at the point's pixel ends no nearer than the
    point minus this (gate/views.py): the planner's z-buffer tolerance, so that a past view
    saw what a candidate view at that pose would have counted."""

    ray_margin_m: float = 0.3
    """gated-ray: a frame exposes a predicted point only when the return at its pixel ends at
    least this far beyond it (the ray passed through it; gate/filter.py, RayGate). Above the
    observed surface's voxel (0.15 m) and the depth noise of the degraded profiles."""
    ray_grazing_max_deg: float = 75.0
    """gated-ray: a return from a surface seen at an incidence angle above this (estimated
    from the depth image's gradient) gives no evidence; 90 turns the test off."""

    ray_inf_k: int = 2
    """gated-ray-inf: its evidence count K (frames whose rays passed through a prediction, a
    return beyond range included). Chosen by the sweep (docs/results/gate-sweep/sweep.md): the
    largest recall at suppression precision 0.9 on the flyer's starts b and c."""
    ray_inf_epsilon_frac: float = 0.06
    """gated-ray-inf: its support radius as a fraction of d_scene (the sweep's choice, as
    ray_inf_k; the frustum gate's is epsilon-frac, 0.03)."""

    split_baseline_m: float = 0.5
    """gated-split: the collision channel withholds a prediction only when rays from two
    camera positions at least this far apart passed through it (gate/filter.py)."""
    pose_sigmas: float = 2.0
    """gated-pose: how many standard deviations of the published pose's covariance a frame
    must tolerate to expose a point, and by which support is widened (gate/filter.py)."""

    def epsilon_m(self, d_scene_m: float) -> float:
        """The support radius epsilon of equation 4, in metres."""
        return self.epsilon_frac * d_scene_m

    def oracle_delta_m(self, d_scene_m: float) -> float:
        """The oracle tagging tolerance delta, in metres (false positives and negatives, and
        the evaluator's audit of what the gate withheld)."""
        return self.oracle_delta_frac * d_scene_m


#: How far inside the planner's local window (``--planner.local-half-m``) the states it may
#: plan through stay: the collision model's ground cells, its plane fits and the body around
#: a state all lie within the window's points (planner/platforms.py).
LOCAL_INSET_M = 10.0


@dataclass
class PlannerConfig:
    """Next-best-view selection and motion planning."""

    name: str = "auto"
    """Planner: beam (the paper's long-horizon search, MAGICIAN-style), greedy (the best next
    view only), or auto: the beam on the flyer, greedy on the rover (where the beam does not
    beat it: see docs/performance.md, *Why `auto` gives the rover the greedy planner*)."""
    n_candidates: int = 32
    """Candidate poses sampled each step within the motion budget (the beam's first level)."""
    beam_width: int = 3
    """Beam search: trajectories kept after each level."""
    beam_depth: int = 3
    """Beam search: steps of look-ahead (1 is the greedy choice over straight motions)."""
    beam_discount: float = 1.0
    """Beam search: the weight of a view's gain is this to the power of its level (0 for the
    first motion): 1 scores a trajectory by its whole gain, below 1 favours the first motion's
    own gain, the one the platform will execute before it replans."""
    beam_branch: int = 8
    """Beam search: candidates sampled from the end of each kept trajectory, after the first
    level."""
    segment_check_m: float = 0.05
    """Beam search: spacing of the collision checks along each look-ahead segment."""
    gain_voxel_m: float = 0.3
    """Edge of the voxels that gather the map into gain primitives (MAGICIAN renders
    Gaussians; we render one weighted primitive per voxel)."""
    max_step_m: float = 3.0
    """Motion budget per step: the longest path the rover drives in one step."""
    gain_resolution: float = 0.25
    """Resolution of gain rendering as a fraction of the sensor's."""
    zbuffer_tolerance_m: float = 0.3
    """A point is visible when it lies at most this far behind the z-buffer's nearest point."""
    observed_min_views: int = 2
    """A map point stops being novel once this many frames have seen its place (its
    ``views``, counted by the gate: gate/views.py)."""
    max_attempts: int = 8
    """Candidates (best gain first) tried with OMPL before giving up on a step."""
    route_blocked: bool = False
    """Beam: also keep a first motion with no straight way there when OMPL reaches it within
    the budget (at most max_attempts such motions a step). Off by default: on the rover it
    helps some scenes and hurts others (docs/roadmap.md), and on the flyer it would change
    the published study's runs."""
    explore_below: int = 0
    """When no candidate's rendered gain reaches this many points, the planner tries them
    farthest from every place the rover stood first (the greedy planner's choice, and the
    beam's when it falls back to it; planner/planner.py, best_feasible), so that a rover whose
    surroundings are all seen heads for ground it has not seen rather than dithering on the
    nearest candidate.
    0 (the default) turns it off: the published studies ran without it, and in a 30 m box the
    gain vanishes only once the box is covered. The soak (benchmarks/bench_long.py) uses 50."""
    local_half_m: float = 50.0
    """Half-side of the square around the vehicle in which the planner reads the map each step
    (its gain, its collision model and the states it may plan through), so that a step costs
    what lies near the vehicle, not the whole map of a long traverse. It must reach the views
    of a step (max_step_m plus the sensor's max_range_m) with margins (planner/platforms.py,
    LOCAL_*); the default covers the whole of any box of interest up to 40 m across from
    anywhere in it, so the suite's missions are the same as with the whole map."""
    ompl_max_checks: int = 3000
    """State-validity checks one OMPL query may spend (a count, not a time, for determinism)."""
    known_free_only: bool = True
    """Flyer: fly only through space known to be free, where a camera ray passed or the
    flyer has been (planner/freespace.py); unknown is not free."""
    free_voxel_m: float = 0.25
    """Voxel of the flyer's known free space."""
    flyer_margin_m: float = 0.2
    """The flyer keeps its sphere this far from every map point. The maps sample surfaces
    about a voxel apart (0.15 m), so an edge can lie 0.2 m from its nearest sample: with a
    0.1 m margin the flyer clipped a slab's corner under ground-truth occupancy."""
    ground_cell_m: float = 0.5
    """Cell of the ground-height grid the collision model derives from the map."""
    obstacle_voxel_m: float = 0.15
    """Edge of the box that each obstacle point becomes in FCL."""
    command: str = ""
    """Run this program as the planner process instead of the built-in one (the mission
    appends --connect ENDPOINT --namespace NS; see docs/writing-a-planner.md). A command line
    whose first word is python or python3 runs with the mission's own interpreter."""
    programs: tuple[str, ...] = ()
    """Planner programs the ground station may swap in by name, fixed at launch: NAME=COMMAND
    entries, e.g. --planner.programs 'frontier=python examples/frontier_planner.py'. The
    ground can only name one of these (or a built-in planner), never send a command line."""


@dataclass
class EvalConfig:
    """Coverage evaluation against ground truth (evaluation only, never fed to the planner)."""

    tau_frac: float = 0.005
    """A true surface sample is covered when an observed point lies within tau = tau_frac *
    d_scene (0.21 m on arch_field: about one mapper voxel diagonal)."""
    n_samples: int = 100_000
    """Ground-truth surface samples, drawn by area with a fixed seed."""


@dataclass
class ContactConfig:
    """Communication with the ground station: contact windows, light time, downlink rate
    (the process set's mission manager; see mission/link/contact.py)."""

    enabled: bool = True
    """Simulate the link and open the ground endpoint (process set only)."""

    period_steps: int = 25
    """A window opens every this many steps..."""
    window_steps: int = 5
    """...and stays open this many steps."""
    first_window_step: int = 0
    """Step at which the first periodic window opens."""
    windows: tuple[str, ...] = ()
    """Explicit windows as START+DURATION in steps (e.g. 10+5 40+3); replaces the periodic
    plan when given."""
    step_s: float = 60.0
    """Simulated seconds per planning step (a 3 m drive, a look around)."""
    light_time_s: float = 90.0
    """One-way light time between the rover and the ground, simulated seconds (Mars: 180 to
    1340 s; this default keeps a command's round trip inside the default window)."""
    downlink_kbps: float = 128.0
    """Downlink rate, kilobits per simulated second."""
    queue_max_mb: float = 64.0
    """Bound on the onboard store-and-forward queue. Over it, the oldest unsent status and
    pose samples are dropped first; events are never dropped (see mission/link/downlink.py)."""
    map_snapshot_points: int = 20_000
    """Most points in one downlinked map snapshot (the observed surface, thinned evenly)."""
    ground_listen: tuple[str, ...] = ()
    """Endpoints where the ground network listens (the mission manager's ground-side session).
    Empty: a free port on 127.0.0.1 (tls/127.0.0.1 with --contact.credentials; port 0 in any
    endpoint also takes a free port), so that missions on one machine never collide. The
    endpoints opened go into OUT/ground.json while the link is up, where `rovergate ground
    --mission OUT` finds them. Without credentials every endpoint must be on loopback; with
    them, every endpoint is tls/ (e.g. tls/0.0.0.0:7448 lets another machine's station in:
    `rovergate ground --credentials DIR/station --connect tls/ROVER:7448`)."""
    credentials: Path | None = None
    """Directory of the rover's ground-link credentials (ca.pem, rover.pem, rover.key; make
    them with `rovergate credentials`): the link is then mutual TLS, and only a station with
    a certificate from the same CA naming one of --contact.ground-stations may command.
    Without it the link is not authenticated and listens on loopback only."""
    ground_stations: tuple[str, ...] = ("station",)
    """Certificate common names of the stations admitted on the link (with credentials)."""
    ground_namespace: str = "ground"
    """Prefix of the ground network's keys."""
    drain_steps: int = 200
    """After the last step, with a ground station connected, keep the clock (and the
    windows) running for at most this many idle steps until all telemetry is acknowledged."""
    idle_step_wall_s: float = 0.05
    """Wall time of one idle step (while paused, or draining after the mission)."""


@dataclass
class MissionConfig:
    """One closed-loop mission."""

    scene: SceneConfig = field(default_factory=SceneConfig)
    platform: str = "rover"
    """rover (SE(2) on the terrain, mast camera) or flyer (a free 6-DoF camera)."""
    start: str = "a"
    """Named start of the scene."""
    steps: int = 100
    """Planning steps T; the run records T+1 coverage values (poses 0..T)."""
    seed: int = 0
    """Seed of every random choice (planner candidates, OMPL sampling)."""
    condition: str = "obs"
    """Planner-facing occupancy: obs, truth, learned, learned-fp, learned+fn, gated."""
    out: Path = Path("runs/latest")
    """Directory for metrics.json, coverage.csv, plots, config.json and logs."""
    in_process: bool = False
    """Run the whole loop in this process without Zenoh (same numbers, no transport)."""
    resume: bool = False
    """Carry on the process-set mission in --out whose mission manager was killed (or that
    failed), from its last step boundary, with the configuration it had then
    (OUT/checkpoint.sqlite, OUT/journal.sqlite; see mission/runtime/checkpoint.py). Give only --out
    (and --no-progress)."""
    ready_timeout_s: float = 120.0
    """How long to wait for every module's liveliness token."""
    step_timeout_s: float = 120.0
    """How long to wait for any one message of a step."""
    max_restarts: int = 3
    """Process set: how many times each module that dies is restarted before the mission
    fails (the loop resumes at the step where it stopped)."""
    progress: bool = True
    """Show a progress bar."""
    record: bool = True
    """Record every topic the modules publish into a rosbag2 bag with MCAP storage,
    OUT/bag/ (ecosystem/recorder.py); `rovergate replay OUT/bag` publishes it again.
    --no-record turns it off (a study's runs are not recorded unless it is given --record)."""
    record_compression: Literal["none", "zstd"] = "none"
    """Compression of the bag's MCAP chunks: none, or zstd (a fifth smaller; its writer
    thread then takes more of the CPU the loop needs: docs/running.md, "The flight recorder and
    replay")."""
    viz: bool = False
    """Serve the mission live to Foxglove (ecosystem/live_view.py): a Foxglove WebSocket
    server on ws://VIZ_HOST:VIZ_PORT; docs/foxglove-layout.json arranges its panels."""
    viz_host: str = "127.0.0.1"
    """Address the live view listens on (0.0.0.0: other machines too; they may only watch)."""
    viz_port: int = 8765
    """Port of the live view (0: any free one; the log says which)."""
    ros2: bool = False
    """Publish the topics into the ROS 2 graph as rmw_zenoh nodes do (ecosystem/ros2.py), via
    the ROS 2 Zenoh router at --ros2-router: `ros2 topic echo /rover/map/occupancy/planner`
    then prints the map. Nothing comes back from ROS 2 this way."""
    ros2_router: str = "tcp/localhost:7447"
    """The ROS 2 Zenoh router (rmw_zenohd) to join."""
    ros2_domain: int = 0
    """The ROS domain id (ROS_DOMAIN_ID) to publish in."""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    sensing: SensingConfig = field(default_factory=SensingConfig)
    rover: RoverConfig = field(default_factory=RoverConfig)
    hazcam: HazcamConfig = field(default_factory=HazcamConfig)
    traverse: TraverseConfig = field(default_factory=TraverseConfig)
    flyer: FlyerConfig = field(default_factory=FlyerConfig)
    mapper: MapperConfig = field(default_factory=MapperConfig)
    gate: GateConfig = field(default_factory=GateConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)
    session: tyro.conf.OmitArgPrefixes[SessionConfig] = field(default_factory=SessionConfig)

    # --- radii derived from the settings: one definition for every module ------------------

    @property
    def vehicle(self) -> Platform:
        """The registered platform ``platform`` names (:mod:`rovergate.platforms`): what it
        has, asked rather than compared by name."""
        return get_platform(self.platform)

    @property
    def tau_m(self) -> float:
        """Coverage tolerance: a true sample is covered with an observed point this near."""
        return self.eval.tau_frac * self.scene.d_scene_m

    @property
    def oracle_delta_m(self) -> float:
        """Oracle tagging tolerance delta of this mission's scene, in metres."""
        return self.gate.oracle_delta_m(self.scene.d_scene_m)


def check_values(cfg: MissionConfig) -> None:
    """Raise :class:`ConfigError` (one line, naming the flag) for a count, limit or range no
    mission can run with. Names (scene, start, condition, planner) are checked where their
    registries live (:func:`mission.run.check_runnable`)."""
    counts: tuple[tuple[str, int, int], ...] = (
            ("--steps", cfg.steps, 1), ("--max-restarts", cfg.max_restarts, 0),
            ("--gate.k", cfg.gate.k, 1), ("--sensor.width-px", cfg.sensor.width_px, 8),
            ("--sensor.height-px", cfg.sensor.height_px, 8),
            ("--planner.n-candidates", cfg.planner.n_candidates, 1),
            ("--planner.beam-width", cfg.planner.beam_width, 1),
            ("--planner.beam-depth", cfg.planner.beam_depth, 1),
            ("--planner.max-attempts", cfg.planner.max_attempts, 1),
            ("--planner.ompl-max-checks", cfg.planner.ompl_max_checks, 1),
            ("--planner.explore-below", cfg.planner.explore_below, 0),
            ("--hazcam.width-px", cfg.hazcam.width_px, 8),
            ("--hazcam.height-px", cfg.hazcam.height_px, 8),
            ("--traverse.backout-steps", cfg.traverse.backout_steps, 0),
            ("--eval.n-samples", cfg.eval.n_samples, 1),
            ("--session.keyframe-every", cfg.session.keyframe_every, 1))
    for flag, count, least in counts:
        if count < least:
            raise ConfigError(f"{flag} must be at least {least}, got {count}")
    for flag, value in (
            ("--ready-timeout-s", cfg.ready_timeout_s), ("--step-timeout-s", cfg.step_timeout_s),
            ("--gate.epsilon-frac", cfg.gate.epsilon_frac),
            ("--gate.oracle-delta-frac", cfg.gate.oracle_delta_frac),
            ("--gate.view-tolerance-m", cfg.gate.view_tolerance_m),
            ("--eval.tau-frac", cfg.eval.tau_frac), ("--mapper.voxel-m", cfg.mapper.voxel_m),
            ("--planner.max-step-m", cfg.planner.max_step_m),
            ("--planner.gain-voxel-m", cfg.planner.gain_voxel_m),
            ("--planner.gain-resolution", cfg.planner.gain_resolution),
            ("--planner.segment-check-m", cfg.planner.segment_check_m),
            ("--planner.free-voxel-m", cfg.planner.free_voxel_m),
            ("--planner.flyer-margin-m", cfg.planner.flyer_margin_m),
            ("--rover.check-spacing-m", cfg.rover.check_spacing_m),
            ("--sensor.min-range-m", cfg.sensor.min_range_m),
            ("--hazcam.min-range-m", cfg.hazcam.min_range_m),
            ("--traverse.cell-m", cfg.traverse.cell_m),
            ("--traverse.mast-range-m", cfg.traverse.mast_range_m),
            ("--traverse.wheel-drop-m", cfg.traverse.wheel_drop_m)):
        if not value > 0:
            raise ConfigError(f"{flag} must be positive, got {value}")
    planner_programs(cfg.planner)
    if cfg.mapper.precision not in ("float32", "bfloat16"):
        raise ConfigError(f"--mapper.precision must be float32 or bfloat16, got "
                          f"{cfg.mapper.precision!r}")
    if cfg.mapper.engine not in ("openvino", "torch"):
        raise ConfigError(f"--mapper.engine must be openvino or torch, got "
                          f"{cfg.mapper.engine!r}")
    if not cfg.sensor.max_range_m > cfg.sensor.min_range_m:
        raise ConfigError(f"--sensor.max-range-m ({cfg.sensor.max_range_m}) must exceed "
                          f"--sensor.min-range-m ({cfg.sensor.min_range_m})")
    reach = (cfg.planner.beam_depth * cfg.planner.max_step_m + cfg.sensor.max_range_m
             + LOCAL_INSET_M)
    if cfg.planner.local_half_m < reach:
        raise ConfigError(f"--planner.local-half-m ({cfg.planner.local_half_m}) must reach a "
                          f"step's views: at least beam-depth x max-step-m + "
                          f"sensor.max-range-m + {LOCAL_INSET_M:g} = {reach:g}")
    if not 0 <= cfg.viz_port <= 65535:
        raise ConfigError(f"--viz-port must be a TCP port (0 to 65535; 0: any free one), got "
                          f"{cfg.viz_port}")
    if not 0 <= cfg.ros2_domain <= 232:
        raise ConfigError(f"--ros2-domain must be a ROS domain id (0 to 232), got "
                          f"{cfg.ros2_domain}")
    if not 0 <= cfg.planner.beam_discount <= 1:
        raise ConfigError(f"--planner.beam-discount must be between 0 and 1, got "
                          f"{cfg.planner.beam_discount}")
    for flag, value in (("--sensor.vfov-deg", cfg.sensor.vfov_deg),
                        ("--hazcam.vfov-deg", cfg.hazcam.vfov_deg)):
        if not 0 < value < 180:
            raise ConfigError(f"{flag} must be between 0 and 180, got {value}")
    if not cfg.hazcam.max_range_m > cfg.hazcam.min_range_m:
        raise ConfigError(f"--hazcam.max-range-m ({cfg.hazcam.max_range_m}) must exceed "
                          f"--hazcam.min-range-m ({cfg.hazcam.min_range_m})")


def planner_programs(planner: PlannerConfig) -> dict[str, str]:
    """``--planner.programs`` as a name -> command line dict; a malformed or repeated entry is
    a :class:`ConfigError` naming it (a built-in planner's name is refused by
    :func:`mission.run.check_runnable`)."""
    out: dict[str, str] = {}
    for entry in planner.programs:
        name, eq, command = entry.partition("=")
        name, command = name.strip(), command.strip()
        if not eq or not name or not command or not name.replace("-", "").replace(
                "_", "").isalnum():
            raise ConfigError(f"--planner.programs entry {entry!r} is not NAME=COMMAND (a "
                              "name of letters, digits, - and _, then the command line)")
        if name in out:
            raise ConfigError(f"--planner.programs names {name!r} twice; give each program "
                              "its own name")
        out[name] = command
    return out


def to_dict(cfg: Any) -> dict[str, Any]:
    """A JSON-ready dict of a config dataclass."""
    def conv(v: Any) -> Any:
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, tuple | list):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        return v
    out: dict[str, Any] = conv(dataclasses.asdict(cfg))
    return out


def changed_settings(cfg: Any, base: Any) -> list[str]:
    """The settings ``cfg`` sets differently from ``base`` (two config dataclasses of one
    kind), as the dotted names the command line takes (``planner.n_candidates``), sorted."""
    def flat(d: dict[str, Any], prefix: str = "") -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {prefix + k: v})
        return out
    given, plain = flat(to_dict(cfg)), flat(to_dict(base))
    return sorted(k for k in given if given[k] != plain.get(k))


def from_dict(cls: type, data: dict[str, Any], where: str = "config") -> Any:
    """Build a config dataclass from a dict, naming any unknown key."""
    hints = typing.get_type_hints(cls, include_extras=True)
    kwargs = {}
    for key, value in data.items():
        f = next((f for f in dataclasses.fields(cls) if f.name == key), None)
        if f is None:
            raise ValueError(f"{where}: unknown key {key!r}")
        hint = hints[key]
        while typing.get_origin(hint) is typing.Annotated:
            hint = typing.get_args(hint)[0]
        if isinstance(hint, type) and dataclasses.is_dataclass(hint):
            kwargs[key] = from_dict(hint, value, f"{where}.{key}")
        elif hint is Path or (hint == Path | None and value is not None):
            kwargs[key] = Path(value)
        elif typing.get_origin(hint) is tuple:
            kwargs[key] = tuple(value)
        else:
            kwargs[key] = value
    return cls(**kwargs)


def save_config(cfg: MissionConfig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(to_dict(cfg), indent=2) + "\n")


#: Settings that no longer exist, dropped from a saved config: ``planner.known_ground_only``
#: (issue 26: the rover's traversability layer refuses unknown ground; the setting trusted
#: predicted ground and had no counterpart left).
RETIRED_KEYS = (("planner", "known_ground_only"),)


def load_config(path: Path) -> MissionConfig:
    """Load a saved config; a bad file gives one line saying what and how to fix it."""
    try:
        data = json.loads(Path(path).read_text())
        for section, key in RETIRED_KEYS:  # a config saved before the key was retired
            if isinstance(data, dict) and isinstance(data.get(section), dict):
                data[section].pop(key, None)
        cfg: MissionConfig = from_dict(MissionConfig, data)
        return cfg
    except FileNotFoundError:
        raise ConfigError(f"config file {path} does not exist; pass the config.json that "
                          "`rovergate run` wrote, or leave --config out") from None
    except (ValueError, TypeError) as exc:
        raise ConfigError(f"config file {path} is not a valid rovergate config ({exc}); "
                          "write it with `rovergate run` or fix the named key") from None
