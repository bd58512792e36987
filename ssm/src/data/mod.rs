//! Datasets: the on-disk format of SPEC §4 (read, validate, write) and importers.
//!
//! A dataset is a directory of CSV files plus `meta.json` (world frame, metres,
//! radians; steps `t = 0..steps`, `steps = T + 1`):
//!
//! | file | columns | required |
//! |---|---|---|
//! | `meta.json` | `{"format": 1, "dt": 0.3333, "steps": T+1}`, optionally `"prior_from_detection": true` | yes |
//! | `av.csv` | `scene,t,x,y,yaw` | yes |
//! | `objects.csv` | `scene,object,length,width,prior_x,prior_y,prior_yaw,prior_v,prior_kappa,sd_x,sd_y,sd_yaw,sd_v,sd_kappa` | yes |
//! | `points.csv` | `scene,object,t,x,y` | one of these two |
//! | `boxes.csv` | `scene,object,t,x,y,yaw,length,width,score` | one of these two |
//! | `states.csv` | `scene,object,t,x,y,yaw,v,kappa` | no |
//! | `actions.csv` | `scene,object,t,accel,pinch` (`t >= 1`) | no |
//!
//! In memory a [`Dataset`] is laid out for the particle filter: scenes sorted by
//! id, objects sorted by (scene, object id) so that each scene's objects are a
//! contiguous range, and every per-(object, step) quantity stored object-major
//! ([`StepTable`], [`PointSets`]) so one object's sequence is one slice.
//! Scene and object ids are the integers of the files.
//!
//! Reading checks everything ([`Dataset::read`]); bad input gives a
//! [`DataError`] naming the file, line and column, never a panic. Writing
//! ([`Dataset::write`]) replaces each file atomically and round-trips bit for
//! bit. [`import_kitti`] turns the KITTI tracking data into box datasets.
//!
//! ```
//! use ssm::data::{Dataset, Meta, ObservationKind, Object, Pose, Prior, State};
//! let meta = Meta::new(0.5, 3);
//! let mut b = Dataset::builder(meta, ObservationKind::Points);
//! b.scene(7, &[Pose { x: 0.0, y: 0.0, yaw: 0.0 }; 3]);
//! let prior = Prior {
//!     mean: State { x: 10.0, y: 2.0, yaw: 0.1, v: 5.0, kappa: 0.0 },
//!     sd: State { x: 1.0, y: 1.0, yaw: 0.1, v: 1.0, kappa: 0.01 },
//! };
//! b.object(Object { scene: 7, id: 42, length: 4.5, width: 1.8, prior });
//! b.point(7, 42, 1, [9.0, 1.5]);
//! b.point(7, 42, 1, [9.5, 2.5]);
//! let ds = b.build().unwrap();
//! assert_eq!(ds.objects().len(), 1);
//! assert_eq!(ds.points().unwrap().get(0, 1), &[[9.0, 1.5], [9.5, 2.5]]);
//! assert!(ds.points().unwrap().get(0, 0).is_empty());
//!
//! let dir = std::env::temp_dir().join(format!("ssm-doc-{}", std::process::id()));
//! ds.write(&dir).unwrap();
//! assert_eq!(Dataset::read(&dir).unwrap(), ds);
//! # std::fs::remove_dir_all(&dir).unwrap();
//! ```

mod builder;
mod error;
mod format;
pub mod kitti;
mod meta;
mod reversals;
mod table;

pub use builder::DatasetBuilder;
pub use error::{DataError, Place, Problem};
pub use kitti::{
    import_kitti, KittiImport, KittiOptions, KittiReport, KittiSplitReport, KITTI_FRAME_DT, KITTI_SCENE_ID_BASE,
    KITTI_VAL_SEQUENCES,
};
pub use reversals::{heading_reversals, HeadingReversals};
pub use table::{PointSets, StepTable};

use serde::{Deserialize, Serialize};
use std::ops::Range;

/// The dataset format version this code reads and writes (`meta.json` `format`).
pub const FORMAT_VERSION: u32 = 1;

/// File name of the metadata.
pub const META_FILE: &str = "meta.json";
/// File name of the AV poses.
pub const AV_FILE: &str = "av.csv";
/// File name of the object list.
pub const OBJECTS_FILE: &str = "objects.csv";
/// File name of point observations.
pub const POINTS_FILE: &str = "points.csv";
/// File name of box-detection observations.
pub const BOXES_FILE: &str = "boxes.csv";
/// File name of ground-truth states.
pub const STATES_FILE: &str = "states.csv";
/// File name of ground-truth actions.
pub const ACTIONS_FILE: &str = "actions.csv";

/// Header of `av.csv`.
pub const AV_COLUMNS: [&str; 5] = ["scene", "t", "x", "y", "yaw"];
/// Header of `objects.csv`.
pub const OBJECT_COLUMNS: [&str; 14] = [
    "scene",
    "object",
    "length",
    "width",
    "prior_x",
    "prior_y",
    "prior_yaw",
    "prior_v",
    "prior_kappa",
    "sd_x",
    "sd_y",
    "sd_yaw",
    "sd_v",
    "sd_kappa",
];
/// Header of `points.csv`.
pub const POINT_COLUMNS: [&str; 5] = ["scene", "object", "t", "x", "y"];
/// Header of `boxes.csv`.
pub const BOX_COLUMNS: [&str; 9] = ["scene", "object", "t", "x", "y", "yaw", "length", "width", "score"];
/// Header of `states.csv`.
pub const STATE_COLUMNS: [&str; 8] = ["scene", "object", "t", "x", "y", "yaw", "v", "kappa"];
/// Header of `actions.csv`.
pub const ACTION_COLUMNS: [&str; 5] = ["scene", "object", "t", "accel", "pinch"];

/// Dataset metadata (`meta.json`; the format version is [`FORMAT_VERSION`]).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Meta {
    /// Time between steps, in seconds (positive).
    pub dt: f64,
    /// Number of steps per scene, `T + 1` (at least 1).
    pub steps: usize,
    /// Each object's prior was read from its first detection (as
    /// [`import_kitti`] does), not known apart from the observations. A model
    /// in which a detection's heading may be reversed
    /// ([`crate::models::extended::Extension::HeadingFlip`]) then takes the prior's
    /// heading as known only up to pi. `false` when absent from `meta.json`.
    #[serde(default)]
    pub prior_from_detection: bool,
}

impl Meta {
    /// Metadata with `dt` and `steps` and a prior not read from a detection.
    pub fn new(dt: f64, steps: usize) -> Meta {
        Meta { dt, steps, prior_from_detection: false }
    }
}

/// A planar pose in the world frame (metres, radians).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position x (m).
    pub x: f64,
    /// Position y (m).
    pub y: f64,
    /// Heading (rad, counter-clockwise from +x).
    pub yaw: f64,
}

/// A vehicle state `(x, y, yaw, v, kappa)`: pose, speed (m/s) and curvature (1/m).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct State {
    /// Position x (m).
    pub x: f64,
    /// Position y (m).
    pub y: f64,
    /// Heading (rad).
    pub yaw: f64,
    /// Speed along the heading (m/s).
    pub v: f64,
    /// Curvature (1/m).
    pub kappa: f64,
}

impl State {
    /// The state as `[x, y, yaw, v, kappa]`.
    pub fn to_array(self) -> [f64; 5] {
        [self.x, self.y, self.yaw, self.v, self.kappa]
    }

    /// A state from `[x, y, yaw, v, kappa]`.
    pub fn from_array(a: [f64; 5]) -> Self {
        State { x: a[0], y: a[1], yaw: a[2], v: a[3], kappa: a[4] }
    }
}

/// An action `(accel, pinch)`: acceleration (m/s²) and rate of change of
/// curvature (1/(m s)), held constant over the step that ends at its `t`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Action {
    /// Acceleration (m/s²).
    pub accel: f64,
    /// Rate of change of curvature (1/(m s)).
    pub pinch: f64,
}

/// The diagonal Gaussian prior of an object's initial state `x_0`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Prior {
    /// Mean of `x_0`.
    pub mean: State,
    /// Standard deviations of `x_0` (all positive).
    pub sd: State,
}

/// One detected box (world frame): centre, heading, extents and detector score.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BoxDetection {
    /// Centre x (m).
    pub x: f64,
    /// Centre y (m).
    pub y: f64,
    /// Heading (rad).
    pub yaw: f64,
    /// Extent along the heading (m, positive).
    pub length: f64,
    /// Extent across the heading (m, positive).
    pub width: f64,
    /// Detector score (any finite value; larger is more confident).
    pub score: f64,
}

/// One road user: its ids, known extents and the prior of its initial state.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Object {
    /// Id of its scene.
    pub scene: i64,
    /// Object id (unique within its scene).
    pub id: i64,
    /// Box length along the heading (m, positive).
    pub length: f64,
    /// Box width (m, positive).
    pub width: f64,
    /// Prior of `x_0`.
    pub prior: Prior,
}

/// A scene: the AV's pose at every step and the range of its objects in
/// [`Dataset::objects`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scene {
    /// Scene id.
    pub id: i64,
    /// AV pose per step (`steps` entries).
    pub av: Vec<Pose>,
    /// Indices of this scene's objects in [`Dataset::objects`].
    pub objects: Range<usize>,
}

/// Which kind of observation a dataset holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ObservationKind {
    /// Sets of 2-D points (`points.csv`).
    Points,
    /// At most one box detection per object and step (`boxes.csv`).
    Boxes,
}

impl ObservationKind {
    fn describe(self) -> &'static str {
        match self {
            ObservationKind::Points => "point observations (points.csv)",
            ObservationKind::Boxes => "box detections (boxes.csv)",
        }
    }
}

/// The observations of every object and step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Observations {
    /// A (possibly empty) point set per object and step.
    Points(PointSets),
    /// At most one box detection per object and step.
    Boxes(StepTable<BoxDetection>),
}

impl Observations {
    /// The kind of observation.
    pub fn kind(&self) -> ObservationKind {
        match self {
            Observations::Points(_) => ObservationKind::Points,
            Observations::Boxes(_) => ObservationKind::Boxes,
        }
    }

    /// Number of observed items: points, or detections.
    pub fn count(&self) -> usize {
        match self {
            Observations::Points(p) => p.len(),
            Observations::Boxes(b) => b.count(),
        }
    }
}

/// A validated dataset in memory (see the [module docs](self) for the layout).
///
/// Built by [`Dataset::read`], [`DatasetBuilder::build`] or an importer; its
/// invariants (every scene has `steps` AV poses, objects sorted and grouped by
/// scene, all values finite, sizes and prior sds positive) always hold.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Dataset {
    meta: Meta,
    scenes: Vec<Scene>,
    objects: Vec<Object>,
    object_scene: Vec<usize>,
    observations: Observations,
    states: Option<StepTable<State>>,
    actions: Option<StepTable<Action>>,
}

/// Where every object of a dataset sits and how much it observes, without its
/// values: what a data-parallel job needs to split the objects between its
/// processes before any of them reads one ([`Dataset::read_layout`],
/// [`Dataset::layout`]).
#[derive(Clone, Debug, PartialEq)]
pub struct DataLayout {
    /// The dataset's `meta.json`.
    pub meta: Meta,
    /// Every object's key `(scene id, object id)`, sorted: the order of
    /// [`Dataset::objects`].
    pub objects: Vec<(i64, i64)>,
    /// Each scene's objects, a range of `objects`, scenes sorted by id.
    pub scenes: Vec<std::ops::Range<usize>>,
    /// Observed items (points, or box detections) of each object
    /// ([`Dataset::object_units`]).
    pub units: Vec<usize>,
}

impl DataLayout {
    /// The layout of sorted `objects` (with `units`) in the sorted scenes
    /// `scene_ids`; every object's scene must be among them.
    pub(crate) fn new(meta: Meta, scene_ids: &[i64], objects: Vec<(i64, i64)>, units: Vec<usize>) -> Self {
        let scenes = scene_ids
            .iter()
            .map(|&id| objects.partition_point(|o| o.0 < id)..objects.partition_point(|o| o.0 <= id))
            .collect();
        DataLayout { meta, objects, scenes, units }
    }
}

impl Dataset {
    /// A builder for a dataset with the given metadata and observation kind.
    pub fn builder(meta: Meta, kind: ObservationKind) -> DatasetBuilder {
        DatasetBuilder::new(meta, kind)
    }

    /// Reads and validates a dataset directory.
    pub fn read(dir: impl AsRef<std::path::Path>) -> Result<Dataset, DataError> {
        format::read_dir(dir.as_ref())
    }

    /// Reads the part of the dataset in `dir` that one process of a
    /// data-parallel job owns: every scene (with its AV poses), and only the
    /// objects whose `(scene, object)` key is in `keep`. The other objects' rows
    /// are skipped unparsed, so a process's memory holds its share; each row is
    /// validated by the process that keeps it. Equal to
    /// [`Dataset::shard`] of the whole dataset for the same objects.
    pub fn read_shard(
        dir: impl AsRef<std::path::Path>,
        keep: &std::collections::HashSet<(i64, i64)>,
    ) -> Result<Dataset, DataError> {
        format::read_shard(dir.as_ref(), keep)
    }

    /// The layout of the dataset in `dir` (its metadata, objects, scenes and
    /// observed items per object), read without parsing any value: the first
    /// pass of a sharded read, and a cheap way to learn a dataset's shape. Equal
    /// to [`Dataset::layout`] of the dataset read whole.
    pub fn read_layout(dir: impl AsRef<std::path::Path>) -> Result<DataLayout, DataError> {
        format::read_layout(dir.as_ref())
    }

    /// The layout of this dataset (see [`DataLayout`]).
    pub fn layout(&self) -> DataLayout {
        DataLayout {
            meta: self.meta,
            objects: self.objects.iter().map(|o| (o.scene, o.id)).collect(),
            scenes: self.scenes.iter().map(|s| s.objects.clone()).collect(),
            units: (0..self.objects.len()).map(|o| self.object_units(o)).collect(),
        }
    }

    /// Writes the dataset into `dir` (created if needed). Each file is written
    /// to a temporary file in `dir` and renamed into place, so a failure never
    /// destroys a file already there. Dataset files this dataset does not have
    /// (the other observation file, `states.csv`, `actions.csv`) are removed
    /// afterwards so the directory reads back as this dataset.
    pub fn write(&self, dir: impl AsRef<std::path::Path>) -> Result<(), DataError> {
        format::write_dir(self, dir.as_ref())
    }

    /// The metadata.
    pub fn meta(&self) -> Meta {
        self.meta
    }

    /// Number of steps per scene (`T + 1`).
    pub fn steps(&self) -> usize {
        self.meta.steps
    }

    /// Time between steps (s).
    pub fn dt(&self) -> f64 {
        self.meta.dt
    }

    /// Observed items (points, or box detections) of `object` over all its steps.
    pub fn object_units(&self, object: usize) -> usize {
        (0..self.steps())
            .map(|t| match &self.observations {
                Observations::Points(p) => p.get(object, t).len(),
                Observations::Boxes(b) => usize::from(b.get(object, t).is_some()),
            })
            .sum()
    }

    /// All scenes, sorted by id.
    pub fn scenes(&self) -> &[Scene] {
        &self.scenes
    }

    /// All objects, sorted by (scene id, object id).
    pub fn objects(&self) -> &[Object] {
        &self.objects
    }

    /// The objects of scene `scene` (an index into [`Dataset::scenes`]).
    #[track_caller]
    pub fn scene_objects(&self, scene: usize) -> &[Object] {
        &self.objects[self.scenes[scene].objects.clone()]
    }

    /// The index (into [`Dataset::scenes`]) of object `object`'s scene.
    #[track_caller]
    pub fn object_scene(&self, object: usize) -> usize {
        self.object_scene[object]
    }

    /// The index of the scene with id `id`.
    pub fn find_scene(&self, id: i64) -> Option<usize> {
        self.scenes.binary_search_by_key(&id, |s| s.id).ok()
    }

    /// The index of object `object` of scene `scene` (ids as in the files).
    pub fn find_object(&self, scene: i64, object: i64) -> Option<usize> {
        self.objects.binary_search_by_key(&(scene, object), |o| (o.scene, o.id)).ok()
    }

    /// The observations.
    pub fn observations(&self) -> &Observations {
        &self.observations
    }

    /// The observation kind.
    pub fn kind(&self) -> ObservationKind {
        self.observations.kind()
    }

    /// The point sets, if this is a point dataset.
    pub fn points(&self) -> Option<&PointSets> {
        match &self.observations {
            Observations::Points(p) => Some(p),
            Observations::Boxes(_) => None,
        }
    }

    /// The box detections, if this is a box dataset.
    pub fn boxes(&self) -> Option<&StepTable<BoxDetection>> {
        match &self.observations {
            Observations::Boxes(b) => Some(b),
            Observations::Points(_) => None,
        }
    }

    /// Ground-truth states, if the dataset has them (cells may be missing).
    pub fn states(&self) -> Option<&StepTable<State>> {
        self.states.as_ref()
    }

    /// Ground-truth actions, if the dataset has them (step 0 is always empty).
    pub fn actions(&self) -> Option<&StepTable<Action>> {
        self.actions.as_ref()
    }

    /// A dataset with only the listed scenes (indices into
    /// [`Dataset::scenes`], in any order; the result is sorted by id again).
    ///
    /// # Panics
    /// If an index is out of range or listed twice (a programmer error).
    #[track_caller]
    pub fn select_scenes(&self, scenes: &[usize]) -> Dataset {
        let mut order: Vec<usize> = scenes.to_vec();
        order.sort_unstable_by_key(|&s| self.scenes[s].id);
        assert!(order.windows(2).all(|w| w[0] != w[1]), "Dataset::select_scenes: a scene is listed twice");
        let objects: Vec<usize> = order.iter().flat_map(|&s| self.scenes[s].objects.clone()).collect();
        self.select(&order, &objects)
    }

    /// A dataset with only the listed objects (indices into [`Dataset::objects`],
    /// in any order) and the scenes that hold at least one of them, each with its
    /// AV poses: the way to split a dataset by object.
    ///
    /// # Panics
    /// If an index is out of range or listed twice (a programmer error).
    #[track_caller]
    pub fn select_objects(&self, objects: &[usize]) -> Dataset {
        let picked = self.sorted_objects(objects, "select_objects");
        let mut scenes: Vec<usize> = picked.iter().map(|&o| self.object_scene[o]).collect();
        scenes.dedup();
        scenes.sort_unstable_by_key(|&s| self.scenes[s].id);
        // Objects in scene order, each scene's in their original order.
        let ordered: Vec<usize> = scenes
            .iter()
            .flat_map(|&s| self.scenes[s].objects.clone().filter(|o| picked.binary_search(o).is_ok()))
            .collect();
        self.select(&scenes, &ordered)
    }

    /// A dataset with every scene (each with its AV poses) and only the listed
    /// objects (indices into [`Dataset::objects`], in any order): one
    /// process's share of a data-parallel job, in memory (see
    /// [`Dataset::read_shard`]). Unlike [`Dataset::select_objects`] it keeps
    /// scenes without objects, so every process sees the same scenes.
    ///
    /// # Panics
    /// If an index is out of range or listed twice (a programmer error).
    #[track_caller]
    pub fn shard(&self, objects: &[usize]) -> Dataset {
        let picked = self.sorted_objects(objects, "shard");
        let scenes: Vec<usize> = (0..self.scenes.len()).collect();
        self.select(&scenes, &picked)
    }

    /// `objects` sorted, checked to be distinct indices into
    /// [`Dataset::objects`]; `caller` names the method in the panic.
    #[track_caller]
    fn sorted_objects(&self, objects: &[usize], caller: &str) -> Vec<usize> {
        let mut picked = objects.to_vec();
        picked.sort_unstable();
        assert!(picked.windows(2).all(|w| w[0] != w[1]), "Dataset::{caller}: an object is listed twice");
        assert!(picked.last().is_none_or(|&o| o < self.objects.len()), "Dataset::{caller}: index out of range");
        picked
    }

    /// The scenes `order` (sorted by id) with the objects `picked` (grouped by
    /// scene in that order).
    fn select(&self, order: &[usize], picked: &[usize]) -> Dataset {
        let mut new_scenes = Vec::with_capacity(order.len());
        let mut object_scene = Vec::with_capacity(picked.len());
        let mut start = 0;
        for (new_index, &s) in order.iter().enumerate() {
            let scene = &self.scenes[s];
            let count = picked[start..].iter().take_while(|&&o| self.object_scene[o] == s).count();
            object_scene.resize(start + count, new_index);
            new_scenes.push(Scene { id: scene.id, av: scene.av.clone(), objects: start..start + count });
            start += count;
        }
        Dataset {
            meta: self.meta,
            scenes: new_scenes,
            objects: picked.iter().map(|&o| self.objects[o]).collect(),
            object_scene,
            observations: match &self.observations {
                Observations::Points(p) => Observations::Points(p.select(picked)),
                Observations::Boxes(b) => Observations::Boxes(b.select(picked)),
            },
            states: self.states.as_ref().map(|s| s.select(picked)),
            actions: self.actions.as_ref().map(|a| a.select(picked)),
        }
    }
}
