//! The paper's ego-centric spatial grid: four 10 m distance bins by twelve lane sectors.
//!
//! The rule (paper appendix, "Actor State Extraction and Filtering"): actors within 40 m; ego
//! frame with x forward and y left; a vehicle whose heading has dot product > 0.5 with the
//! ego's is *same direction*, < -0.5 *opposing*, otherwise *other* (crossing); same-direction
//! vehicles go to the in-lane, left or right lane by lateral offset with a 3 m lane width; and
//! ahead / beside / behind comes from the ego's forward vector and the relative position.
//!
//! Choices where the paper is silent (settings of [`GridRule`]): a vehicle is *beside* when its
//! longitudinal offset is within `beside_m` (2.5 m: about half a car length) of the ego's centre;
//! only the left and right lanes have beside sectors, so an in-lane, opposing or other vehicle
//! within the band counts as front when x >= 0. Lanes further out than the adjacent ones count
//! as left or right. Direction compares body headings by default (the paper's "forward
//! vectors"); `heading = "lane"` compares the headings of the lanes the two drive in instead, so
//! a vehicle changing lanes or turning keeps its lane's direction (where the Scenes artifact
//! records no lane, the body heading stands in).

use serde::{Deserialize, Serialize};

/// The distance bins' JSON keys, nearest first.
pub const DISTANCE_BINS: [&str; 4] = ["0-10m", "10-20m", "20-30m", "30-40m"];
pub const BIN_WIDTH_M: f64 = 10.0;
pub const MAX_RANGE_M: f64 = 40.0;

/// The twelve sector keys, in the paper's order.
pub const SECTORS: [&str; 12] = [
    "left_lane_front_side",
    "left_side",
    "left_lane_back_side",
    "in_lane_front_side",
    "in_lane_back_side",
    "right_lane_front_side",
    "right_side",
    "right_lane_back_side",
    "opposing_lane_front",
    "opposing_lane_back",
    "other_lane_front",
    "other_lane_back",
];

/// Cells in the count vector: `bin * 12 + sector`.
pub const CELLS: usize = DISTANCE_BINS.len() * SECTORS.len();

/// The classification rule's thresholds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GridRule {
    /// Lateral width of a lane, 0.5..=20 m: |y| <= lane_width_m / 2 is the ego's lane.
    pub lane_width_m: f64,
    /// Heading dot product above which a vehicle is same-direction (below minus it: opposing),
    /// in [0, 1).
    pub direction_dot: f64,
    /// Half-width of the beside band along x, 0..=10 m.
    pub beside_m: f64,
    /// Which headings the direction test compares.
    pub heading: Heading,
}

/// The headings the direction test compares: the vehicles' bodies, or their lanes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Heading {
    #[default]
    Body,
    Lane,
}

impl Default for GridRule {
    fn default() -> Self {
        GridRule { lane_width_m: 3.0, direction_dot: 0.5, beside_m: 2.5, heading: Heading::Body }
    }
}

/// A cell: distance bin and sector index.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Cell {
    pub bin: usize,
    pub sector: usize,
}

impl Cell {
    pub fn index(&self) -> usize {
        self.bin * SECTORS.len() + self.sector
    }

    pub fn from_index(i: usize) -> Cell {
        Cell { bin: i / SECTORS.len(), sector: i % SECTORS.len() }
    }

    pub fn name(&self) -> String {
        format!("{}/{}", DISTANCE_BINS[self.bin], SECTORS[self.sector])
    }
}

impl GridRule {
    /// The heading the direction test uses for a vehicle with this body heading and lane
    /// heading (both relative to the ego's).
    pub fn direction(&self, body: f64, lane: Option<f64>) -> f64 {
        match (self.heading, lane) {
            (Heading::Lane, Some(lane)) => lane,
            _ => body,
        }
    }

    /// The cell of a vehicle at ego-frame position (x, y) with heading `heading` relative to
    /// the ego's; `None` beyond 40 m.
    pub fn classify(&self, x: f64, y: f64, heading: f64) -> Option<Cell> {
        let distance = (x * x + y * y).sqrt();
        if distance >= MAX_RANGE_M {
            return None;
        }
        let bin = ((distance / BIN_WIDTH_M) as usize).min(DISTANCE_BINS.len() - 1);
        let dot = heading.cos();
        let ahead = x >= 0.0;
        let beside = x.abs() <= self.beside_m;
        let half = self.lane_width_m / 2.0;
        let sector = if dot > self.direction_dot {
            match (y > half, y < -half) {
                (true, _) if beside => 1,
                (true, _) => {
                    if ahead {
                        0
                    } else {
                        2
                    }
                }
                (_, true) if beside => 6,
                (_, true) => {
                    if ahead {
                        5
                    } else {
                        7
                    }
                }
                _ => {
                    if ahead {
                        3
                    } else {
                        4
                    }
                }
            }
        } else if dot < -self.direction_dot {
            if ahead { 8 } else { 9 }
        } else if ahead {
            10
        } else {
            11
        };
        Some(Cell { bin, sector })
    }
}

/// One frame's grid: vehicles per cell, walkers, applicable traffic signs.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Grid {
    /// Indexed by [`Cell::index`].
    pub counts: [u32; CELLS],
    pub walkers: u32,
    pub signs: Vec<String>,
}

impl Default for Grid {
    fn default() -> Self {
        Grid { counts: [0; CELLS], walkers: 0, signs: Vec::new() }
    }
}

impl Grid {
    pub fn get(&self, bin: usize, sector: usize) -> u32 {
        self.counts[Cell { bin, sector }.index()]
    }

    pub fn set(&mut self, bin: usize, sector: usize, n: u32) {
        self.counts[Cell { bin, sector }.index()] = n;
    }

    pub fn bin_total(&self, bin: usize) -> u32 {
        (0..SECTORS.len()).map(|s| self.get(bin, s)).sum()
    }

    pub fn vehicles(&self) -> u32 {
        self.counts.iter().sum()
    }

    /// The paper's JSON, keys in the paper's order: per bin `total_vehicles` then the non-zero
    /// sectors; then `traffic_signs` and `walkers`.
    pub fn to_json(&self) -> String {
        let mut out = String::from("{");
        for (bin, name) in DISTANCE_BINS.iter().enumerate() {
            out += &format!("\"{name}\":{{\"total_vehicles\":{}", self.bin_total(bin));
            for (sector, key) in SECTORS.iter().enumerate() {
                let n = self.get(bin, sector);
                if n > 0 {
                    out += &format!(",\"{key}\":{n}");
                }
            }
            out += "},";
        }
        out += &format!("\"traffic_signs\":{},\"walkers\":{}}}", serde_json::to_string(&self.signs).expect("strings"), self.walkers);
        out
    }

    /// Reads the paper's JSON (also `applicable_traffic_signs`, the prompt's spelling). A bin's
    /// `total_vehicles` must equal the sum of its sectors.
    pub fn from_json(value: &serde_json::Value) -> Result<Grid, String> {
        let object = value.as_object().ok_or("a grid is a JSON object")?;
        let mut grid = Grid::default();
        for (key, v) in object {
            if let Some(bin) = DISTANCE_BINS.iter().position(|b| b == key) {
                let sectors = v.as_object().ok_or_else(|| format!("`{key}` must be an object"))?;
                let mut total = None;
                for (k, n) in sectors {
                    let n = n.as_u64().ok_or_else(|| format!("`{key}.{k}` must be a count"))? as u32;
                    match SECTORS.iter().position(|s| s == k) {
                        Some(sector) => grid.set(bin, sector, n),
                        None if k == "total_vehicles" => total = Some(n),
                        None => return Err(format!("unknown key `{key}.{k}`; valid: total_vehicles, {}", SECTORS.join(", "))),
                    }
                }
                if let Some(t) = total.filter(|&t| t != grid.bin_total(bin)) {
                    return Err(format!("`{key}.total_vehicles` is {t} but its sectors add up to {}", grid.bin_total(bin)));
                }
            } else if key == "walkers" {
                grid.walkers = v.as_u64().ok_or("`walkers` must be a count")? as u32;
            } else if key == "traffic_signs" || key == "applicable_traffic_signs" {
                grid.signs = serde_json::from_value(v.clone()).map_err(|_| format!("`{key}` must be a list of strings"))?;
            } else {
                return Err(format!("unknown key `{key}`; valid: {}, traffic_signs, walkers", DISTANCE_BINS.join(", ")));
            }
        }
        Ok(grid)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn the_papers_json_reads_and_writes_back() {
        let text = r#"{"0-10m":{"total_vehicles":3,"in_lane_front_side":1,"right_lane_back_side":2},"10-20m":{"total_vehicles":5,"in_lane_back_side":1,"right_lane_front_side":3,"right_lane_back_side":1},"20-30m":{"total_vehicles":4,"opposing_lane_front":4},"30-40m":{"total_vehicles":2,"in_lane_front_side":1,"right_lane_front_side":1},"traffic_signs":[],"walkers":0}"#;
        let grid = Grid::from_json(&serde_json::from_str(text).unwrap()).unwrap();
        assert_eq!(grid.vehicles(), 14);
        assert_eq!(grid.get(2, 8), 4);
        assert_eq!(grid.to_json(), text);
        let bad = serde_json::json!({"0-10m": {"total_vehicles": 2, "left_side": 1}});
        assert_eq!(Grid::from_json(&bad).unwrap_err(), "`0-10m.total_vehicles` is 2 but its sectors add up to 1");
    }

    #[test]
    fn the_paper_rule_classifies_each_sector() {
        let r = GridRule::default();
        let name = |x, y, h| r.classify(x, y, h).map(|c| c.name());
        assert_eq!(name(5.0, 0.3, 0.1).unwrap(), "0-10m/in_lane_front_side");
        assert_eq!(name(-15.0, -0.5, 0.0).unwrap(), "10-20m/in_lane_back_side");
        assert_eq!(name(12.0, 3.5, 0.0).unwrap(), "10-20m/left_lane_front_side");
        assert_eq!(name(1.0, 3.5, 0.0).unwrap(), "0-10m/left_side");
        assert_eq!(name(-25.0, 7.0, 0.2).unwrap(), "20-30m/left_lane_back_side");
        assert_eq!(name(0.0, -3.5, 0.0).unwrap(), "0-10m/right_side");
        assert_eq!(name(31.0, -3.5, -0.3).unwrap(), "30-40m/right_lane_front_side");
        assert_eq!(name(-8.0, -3.5, 0.0).unwrap(), "0-10m/right_lane_back_side");
        assert_eq!(name(22.0, 7.0, PI).unwrap(), "20-30m/opposing_lane_front");
        assert_eq!(name(-5.0, 7.0, PI - 0.2).unwrap(), "0-10m/opposing_lane_back");
        assert_eq!(name(14.0, -6.0, PI / 2.0).unwrap(), "10-20m/other_lane_front");
        assert_eq!(name(-35.0, 2.0, -PI / 2.0).unwrap(), "30-40m/other_lane_back");
        assert_eq!(name(40.0, 0.0, 0.0), None);
        assert_eq!(Cell::from_index(Cell { bin: 3, sector: 11 }.index()), Cell { bin: 3, sector: 11 });
    }
}
