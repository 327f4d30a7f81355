"""Traffic from highway-env, driven headless for the `highway-env` scenes operator.

highway-env is used as a traffic library: its road networks, IDM/MOBIL vehicles and lane
geometry. Every vehicle, the environment's own ego included, drives itself (IDM), and the
simulation advances with road.act(); road.step(dt). The Rust side picks the ego per frame and
renders the radar; this module only steps traffic and returns flat arrays.

World coordinates are highway-env's (x right, y down on screen). Rows of `state()`:
id, x, y, heading, length, width, speed, is_truck, lane heading (the heading of the lane the
vehicle is on, at its position).
"""

import gymnasium as gym
import highway_env  # noqa: F401  (registers the environments)
import numpy as np
from highway_env.road.lane import LineType, StraightLane
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle

def lane_heading(v):
    """The heading of the lane `v` is on, at its position (its own heading off the road)."""
    if v.lane is None:
        return v.heading
    return v.lane.heading_at(v.lane.local_coordinates(v.position)[0])


ENVIRONMENTS = {
    "highway": "highway-v0",
    "merge": "merge-v1",
    "roundabout": "roundabout-v1",
    "intersection": "intersection-v2",
    "two-way": "two-way-v0",
}
# Vehicles kept on the road per scenario at density 1.
BASE_VEHICLES = {"highway": 40, "merge": 16, "roundabout": 14, "intersection": 16, "two-way": 14, "divided": 30}
SIMULATION_HZ = 15
TRUCK = (10.0, 2.5)
SPAWN_GAP_M = 12.0


def divided_highway(lanes=3, width=4.0, median=6.0, length=2000.0, speed=30.0):
    """A divided two-way highway: `lanes` lanes each way, a median between."""
    net = RoadNetwork()
    c, s, n = LineType.CONTINUOUS_LINE, LineType.STRIPED, LineType.NONE
    for i in range(lanes):
        y = i * width
        sides = (c if i == 0 else s, c if i == lanes - 1 else n)
        net.add_lane("a", "b", StraightLane([0, y], [length, y], line_types=sides, speed_limit=speed))
        # Oncoming lanes lie to the drivers' left (negative y): right-hand traffic.
        y = -(width + median + i * width)
        sides = (c if i == 0 else s, c if i == lanes - 1 else n)
        net.add_lane("b", "a", StraightLane([length, y], [0, y], line_types=sides, speed_limit=speed))
    return net


class Simulation:
    def __init__(self, scenario, seed, density, truck_fraction):
        self.rng = np.random.default_rng(seed)
        self.truck_fraction = truck_fraction
        self.target = max(1, int(round(BASE_VEHICLES[scenario] * density)))
        self.next_id = 1
        if scenario == "divided":
            self.road = Road(network=divided_highway(), np_random=self.rng, record_history=False)
            lane = self.road.network.get_lane(("a", "b", 1))
            ego = IDMVehicle(self.road, lane.position(300.0, 0.0), heading=lane.heading_at(300.0), speed=25.0)
            self.road.vehicles.append(ego)
        else:
            config = {"simulation_frequency": SIMULATION_HZ}
            if scenario == "highway":
                config.update(vehicles_count=self.target, vehicles_density=density, lanes_count=4)
            if scenario == "intersection":
                config.update(initial_vehicle_count=self.target)
            env = gym.make(ENVIRONMENTS[scenario], render_mode=None, config=config)
            env.reset(seed=int(seed % 2**31))
            u = env.unwrapped
            self.road = u.road
            ego = u.vehicle
            # The environment's ego drives itself too.
            index = self.road.vehicles.index(ego)
            ego = IDMVehicle.create_from(ego)
            self.road.vehicles[index] = ego
            self.road.vehicles.insert(0, self.road.vehicles.pop(index))
        self.dt = 1.0 / SIMULATION_HZ
        self.lanes = list(self._lanes())
        for v in self.road.vehicles:
            self._adopt(v)
        self._refill()

    def _lanes(self):
        for a, ends in self.road.network.graph.items():
            for b, lanes in ends.items():
                for i, lane in enumerate(lanes):
                    yield (a, b, i), lane

    def _adopt(self, v):
        # The id lives on the vehicle, never keyed by id(v): a removed vehicle's address can be
        # reused by a new one, which then would skip its truck draw, and addresses differ between
        # processes, so the scene would depend on the allocator.
        if getattr(v, "rlmflow_id", None) is None:
            v.rlmflow_id = self.next_id
            self.next_id += 1
            if self.rng.random() < self.truck_fraction:
                v.LENGTH, v.WIDTH = TRUCK
                v.is_truck = True

    def _refill(self):
        """Drops vehicles that left the road or crashed; spawns new ones near existing traffic
        until the scenario's count is reached."""
        ego = self.road.vehicles[0]
        self.road.vehicles = [ego] + [v for v in self.road.vehicles[1:] if v.on_road and not v.crashed]
        for _ in range(4 * self.target):
            if len(self.road.vehicles) >= self.target:
                break
            anchor = self.road.vehicles[self.rng.integers(len(self.road.vehicles))]
            near = []
            for key, lane in self.lanes:
                along, lateral = lane.local_coordinates(anchor.position)
                if abs(lateral) < 40 and -60 < along < lane.length + 60:
                    near.append((key, lane, along))
            if not near:
                continue
            key, lane, along = near[self.rng.integers(len(near))]
            s = along + self.rng.uniform(-70.0, 70.0)
            if not 0.0 <= s <= lane.length:
                continue
            position = lane.position(s, 0.0)
            if any(np.linalg.norm(v.position - position) < SPAWN_GAP_M for v in self.road.vehicles):
                continue
            limit = lane.speed_limit or 20.0
            v = IDMVehicle(self.road, position, heading=lane.heading_at(s), speed=limit * self.rng.uniform(0.6, 0.95), target_lane_index=key)
            v.randomize_behavior()
            self.road.vehicles.append(v)
            self._adopt(v)

    def step(self, steps):
        for _ in range(steps):
            self.road.act()
            self.road.step(self.dt)
        self._refill()

    def state(self):
        rows = [
            (v.rlmflow_id, v.position[0], v.position[1], v.heading, v.LENGTH, v.WIDTH, v.speed, float(getattr(v, "is_truck", False)), lane_heading(v))
            for v in self.road.vehicles
        ]
        return np.asarray(rows, dtype=np.float64).tobytes()

    def edges(self, spacing=10.0):
        """Road edges (solid outer lines) as segments of at most `spacing` metres:
        x0, y0, x1, y1 per segment."""
        out = []
        for _, lane in self.lanes:
            for side, offset in ((0, -0.5), (1, 0.5)):
                if lane.line_types[side] not in (LineType.CONTINUOUS, LineType.CONTINUOUS_LINE):
                    continue
                n = max(1, int(np.ceil(lane.length / spacing)))
                points = [lane.position(lane.length * i / n, offset * lane.width_at(lane.length * i / n)) for i in range(n + 1)]
                for p, q in zip(points, points[1:]):
                    out.append((p[0], p[1], q[0], q[1]))
        return np.asarray(out, dtype=np.float64).reshape(-1, 4).tobytes()
