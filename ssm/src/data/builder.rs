//! Building a [`Dataset`] from records, with every check of SPEC §4.
//!
//! The file reader and the in-memory builder share this code: records carry
//! their [`Place`] (a file line, or the index of an in-memory record), so one
//! validation pass serves both and its errors say where the bad record is.

use super::error::{DataError, Place, Problem};
use super::table::{PointSets, StepTable};
use super::{
    Action, BoxDetection, Dataset, Meta, Object, ObservationKind, Observations, Pose, Scene, State, ACTIONS_FILE,
    ACTION_COLUMNS, AV_COLUMNS, AV_FILE, BOXES_FILE, BOX_COLUMNS, OBJECTS_FILE, OBJECT_COLUMNS, POINTS_FILE,
    POINT_COLUMNS, STATES_FILE, STATE_COLUMNS,
};
use std::collections::HashMap;

/// One record keyed by scene, object and step (fields a kind does not use are 0).
#[derive(Clone, Debug)]
pub(crate) struct Rec<T> {
    pub place: Place,
    pub scene: i64,
    pub object: i64,
    pub t: i64,
    pub value: T,
}

/// All records of a dataset, before validation.
#[derive(Clone, Debug, Default)]
pub(crate) struct Records {
    pub av: Vec<Rec<Pose>>,
    pub objects: Vec<Rec<Object>>,
    pub points: Vec<Rec<[f64; 2]>>,
    pub boxes: Vec<Rec<BoxDetection>>,
    pub states: Option<Vec<Rec<State>>>,
    pub actions: Option<Vec<Rec<Action>>>,
}

/// Builds a [`Dataset`] in memory, record by record, in any order.
///
/// Adding never fails; [`DatasetBuilder::build`] runs the same checks as
/// reading files and reports a bad record by kind (the file it would be
/// written to), index ([`Place::Record`]) and column.
#[derive(Clone, Debug)]
pub struct DatasetBuilder {
    meta: Meta,
    kind: ObservationKind,
    records: Records,
}

impl DatasetBuilder {
    /// A builder for a dataset with the given metadata and observation kind.
    pub fn new(meta: Meta, kind: ObservationKind) -> Self {
        DatasetBuilder { meta, kind, records: Records::default() }
    }

    /// Adds a scene with the AV pose at each step (`av.len()` must be `steps`).
    pub fn scene(&mut self, id: i64, av: &[Pose]) -> &mut Self {
        for (t, pose) in av.iter().enumerate() {
            let place = Place::Record(self.records.av.len());
            self.records.av.push(Rec { place, scene: id, object: 0, t: t as i64, value: *pose });
        }
        self
    }

    /// Adds an object (its `scene` field names its scene).
    pub fn object(&mut self, object: Object) -> &mut Self {
        let place = Place::Record(self.records.objects.len());
        self.records.objects.push(Rec { place, scene: object.scene, object: object.id, t: 0, value: object });
        self
    }

    /// Adds one observed point of object `object` of scene `scene` at step `t`.
    pub fn point(&mut self, scene: i64, object: i64, t: usize, xy: [f64; 2]) -> &mut Self {
        let place = Place::Record(self.records.points.len());
        self.records.points.push(rec(place, scene, object, t, xy));
        self
    }

    /// Adds the box detection of object `object` of scene `scene` at step `t`.
    pub fn detection(&mut self, scene: i64, object: i64, t: usize, detection: BoxDetection) -> &mut Self {
        let place = Place::Record(self.records.boxes.len());
        self.records.boxes.push(rec(place, scene, object, t, detection));
        self
    }

    /// Adds the ground-truth state of an object at step `t`.
    pub fn state(&mut self, scene: i64, object: i64, t: usize, state: State) -> &mut Self {
        let v = self.records.states.get_or_insert_with(Vec::new);
        v.push(rec(Place::Record(v.len()), scene, object, t, state));
        self
    }

    /// Adds the ground-truth action of an object at step `t >= 1` (the action
    /// applied between steps `t - 1` and `t`).
    pub fn action(&mut self, scene: i64, object: i64, t: usize, action: Action) -> &mut Self {
        let v = self.records.actions.get_or_insert_with(Vec::new);
        v.push(rec(Place::Record(v.len()), scene, object, t, action));
        self
    }

    /// Declares that the dataset has ground truth states even if none are added.
    pub fn with_states(&mut self) -> &mut Self {
        self.records.states.get_or_insert_with(Vec::new);
        self
    }

    /// Declares that the dataset has ground truth actions even if none are added.
    pub fn with_actions(&mut self) -> &mut Self {
        self.records.actions.get_or_insert_with(Vec::new);
        self
    }

    /// Validates the records and builds the dataset.
    pub fn build(self) -> Result<Dataset, DataError> {
        let meta_line = 1;
        super::meta::check_meta(&self.meta, meta_line)?;
        assemble(self.meta, self.kind, self.records)
    }
}

fn rec<T>(place: Place, scene: i64, object: i64, t: usize, value: T) -> Rec<T> {
    Rec { place, scene, object, t: i64::try_from(t).unwrap_or(i64::MAX), value }
}

/// Checks that a value is finite.
fn finite(file: &str, place: Place, column: &str, v: f64) -> Result<(), DataError> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(DataError::invalid(file, place, column, Problem::NonFinite { text: format!("{v}") }))
    }
}

/// Checks that a value is finite and positive.
fn positive(file: &str, place: Place, column: &str, v: f64) -> Result<(), DataError> {
    finite(file, place, column, v)?;
    if v > 0.0 {
        Ok(())
    } else {
        Err(DataError::invalid(file, place, column, Problem::NonPositive { value: v }))
    }
}

/// Checks that `t` lies in `lo..hi`.
fn step(file: &str, place: Place, t: i64, lo: usize, hi: usize) -> Result<usize, DataError> {
    if t >= lo as i64 && t < hi as i64 {
        Ok(t as usize)
    } else {
        Err(DataError::invalid(file, place, "t", Problem::StepOutOfRange { t, lo, hi }))
    }
}

/// Finds an object, naming `scene` or `object` as the bad column.
fn lookup(
    file: &str,
    place: Place,
    scene: i64,
    object: i64,
    scenes: &HashMap<i64, usize>,
    objects: &HashMap<(i64, i64), usize>,
) -> Result<usize, DataError> {
    if !scenes.contains_key(&scene) {
        return Err(DataError::invalid(file, place, "scene", Problem::UnknownScene { scene }));
    }
    objects
        .get(&(scene, object))
        .copied()
        .ok_or_else(|| DataError::invalid(file, place, "object", Problem::UnknownObject { scene, object }))
}

/// Fills a [`StepTable`] from keyed records, checking keys, steps, duplicates
/// and each value (with `check`).
#[allow(clippy::too_many_arguments)]
fn fill_table<T: Clone>(
    file: &str,
    recs: &[Rec<T>],
    first_step: usize,
    steps: usize,
    scenes: &HashMap<i64, usize>,
    objects: &HashMap<(i64, i64), usize>,
    n_objects: usize,
    check: impl Fn(Place, &T) -> Result<(), DataError>,
) -> Result<StepTable<T>, DataError> {
    let mut table = StepTable::new(n_objects, steps);
    let mut first_place: HashMap<(usize, usize), Place> = HashMap::new();
    for r in recs {
        let o = lookup(file, r.place, r.scene, r.object, scenes, objects)?;
        let t = step(file, r.place, r.t, first_step, steps)?;
        check(r.place, &r.value)?;
        if let Some(first) = first_place.insert((o, t), r.place) {
            return Err(DataError::invalid(
                file,
                r.place,
                "t",
                Problem::Duplicate { key: format!("scene {}, object {}, t {}", r.scene, r.object, t), first },
            ));
        }
        table.set(o, t, r.value.clone());
    }
    Ok(table)
}

/// Validates all records and lays them out as a [`Dataset`]. `meta` must
/// already be valid.
pub(crate) fn assemble(meta: Meta, kind: ObservationKind, records: Records) -> Result<Dataset, DataError> {
    let steps = meta.steps;

    // --- av.csv: scenes and their poses. Rows are gathered per scene and
    // sorted by step (stable, so a duplicate is reported at its second
    // occurrence); nothing is allocated per step before the rows show that
    // the steps exist, so a huge `steps` in meta.json cannot exhaust memory.
    struct SceneAcc {
        first: Place,
        rows: Vec<(usize, Pose, Place)>,
    }
    let mut scene_acc: HashMap<i64, SceneAcc> = HashMap::new();
    let mut scene_order: Vec<i64> = Vec::new();
    for r in &records.av {
        let t = step(AV_FILE, r.place, r.t, 0, steps)?;
        let p = r.value;
        for (col, v) in AV_COLUMNS[2..].iter().zip([p.x, p.y, p.yaw]) {
            finite(AV_FILE, r.place, col, v)?;
        }
        let acc = scene_acc.entry(r.scene).or_insert_with(|| {
            scene_order.push(r.scene);
            SceneAcc { first: r.place, rows: Vec::new() }
        });
        acc.rows.push((t, p, r.place));
    }
    // Problems are reported scene by scene, in order of first appearance.
    for id in &scene_order {
        let acc = scene_acc.get_mut(id).expect("scene was collected");
        acc.rows.sort_by_key(|row| row.0);
        for w in acc.rows.windows(2) {
            if w[0].0 == w[1].0 {
                return Err(DataError::invalid(
                    AV_FILE,
                    w[1].2,
                    "t",
                    Problem::Duplicate { key: format!("scene {id}, t {}", w[1].0), first: w[0].2 },
                ));
            }
        }
        if acc.rows.len() < steps {
            let t = acc.rows.iter().enumerate().find(|(i, row)| row.0 != *i).map_or(acc.rows.len(), |(i, _)| i);
            return Err(DataError::invalid(AV_FILE, acc.first, "t", Problem::MissingStep { scene: *id, t }));
        }
    }
    scene_order.sort_unstable();
    let scene_index: HashMap<i64, usize> = scene_order.iter().enumerate().map(|(i, &id)| (id, i)).collect();

    // --- objects.csv.
    let mut seen: HashMap<(i64, i64), Place> = HashMap::new();
    for r in &records.objects {
        let o = &r.value;
        if !scene_index.contains_key(&o.scene) {
            return Err(DataError::invalid(OBJECTS_FILE, r.place, "scene", Problem::UnknownScene { scene: o.scene }));
        }
        if let Some(&first) = seen.get(&(o.scene, o.id)) {
            return Err(DataError::invalid(
                OBJECTS_FILE,
                r.place,
                "object",
                Problem::Duplicate { key: format!("scene {}, object {}", o.scene, o.id), first },
            ));
        }
        seen.insert((o.scene, o.id), r.place);
        let m = o.prior.mean.to_array();
        let s = o.prior.sd.to_array();
        positive(OBJECTS_FILE, r.place, "length", o.length)?;
        positive(OBJECTS_FILE, r.place, "width", o.width)?;
        for (col, v) in OBJECT_COLUMNS[4..9].iter().zip(m) {
            finite(OBJECTS_FILE, r.place, col, v)?;
        }
        for (col, v) in OBJECT_COLUMNS[9..].iter().zip(s) {
            positive(OBJECTS_FILE, r.place, col, v)?;
        }
    }
    let mut objects: Vec<Object> = records.objects.iter().map(|r| r.value).collect();
    objects.sort_unstable_by_key(|o| (o.scene, o.id));
    let object_index: HashMap<(i64, i64), usize> =
        objects.iter().enumerate().map(|(i, o)| ((o.scene, o.id), i)).collect();
    let object_scene: Vec<usize> = objects.iter().map(|o| scene_index[&o.scene]).collect();
    let mut scenes: Vec<Scene> = Vec::with_capacity(scene_order.len());
    let mut next = 0;
    for (si, id) in scene_order.iter().enumerate() {
        let start = next;
        while next < objects.len() && object_scene[next] == si {
            next += 1;
        }
        let acc = scene_acc.remove(id).expect("scene was collected");
        scenes.push(Scene { id: *id, av: acc.rows.into_iter().map(|row| row.1).collect(), objects: start..next });
    }
    let n = objects.len();

    // --- observations.
    let wrong_kind = |file: &str, place: Place| {
        DataError::invalid(file, place, "scene", Problem::WrongKind { dataset: kind.describe() })
    };
    let observations = match kind {
        ObservationKind::Points => {
            if let Some(r) = records.boxes.first() {
                return Err(wrong_kind(BOXES_FILE, r.place));
            }
            let mut cells = Vec::with_capacity(records.points.len());
            // Consecutive points usually share an object: skip the hash lookups then.
            let mut last: Option<((i64, i64), usize)> = None;
            for r in &records.points {
                let o = match last {
                    Some((key, o)) if key == (r.scene, r.object) => o,
                    _ => lookup(POINTS_FILE, r.place, r.scene, r.object, &scene_index, &object_index)?,
                };
                last = Some(((r.scene, r.object), o));
                let t = step(POINTS_FILE, r.place, r.t, 0, steps)?;
                finite(POINTS_FILE, r.place, POINT_COLUMNS[3], r.value[0])?;
                finite(POINTS_FILE, r.place, POINT_COLUMNS[4], r.value[1])?;
                cells.push((o, t, r.value));
            }
            Observations::Points(PointSets::from_triples(n, steps, cells.iter().copied()))
        }
        ObservationKind::Boxes => {
            if let Some(r) = records.points.first() {
                return Err(wrong_kind(POINTS_FILE, r.place));
            }
            Observations::Boxes(fill_table(
                BOXES_FILE,
                &records.boxes,
                0,
                steps,
                &scene_index,
                &object_index,
                n,
                |place, b: &BoxDetection| {
                    for (col, v) in BOX_COLUMNS[3..6].iter().zip([b.x, b.y, b.yaw]) {
                        finite(BOXES_FILE, place, col, v)?;
                    }
                    positive(BOXES_FILE, place, "length", b.length)?;
                    positive(BOXES_FILE, place, "width", b.width)?;
                    finite(BOXES_FILE, place, "score", b.score)
                },
            )?)
        }
    };

    // --- ground truth.
    let states = match &records.states {
        None => None,
        Some(recs) => {
            Some(fill_table(STATES_FILE, recs, 0, steps, &scene_index, &object_index, n, |place, s: &State| {
                for (col, v) in STATE_COLUMNS[3..].iter().zip(s.to_array()) {
                    finite(STATES_FILE, place, col, v)?;
                }
                Ok(())
            })?)
        }
    };
    let actions = match &records.actions {
        None => None,
        Some(recs) => {
            Some(fill_table(ACTIONS_FILE, recs, 1, steps, &scene_index, &object_index, n, |place, a: &Action| {
                finite(ACTIONS_FILE, place, ACTION_COLUMNS[3], a.accel)?;
                finite(ACTIONS_FILE, place, ACTION_COLUMNS[4], a.pinch)
            })?)
        }
    };

    Ok(Dataset { meta, scenes, objects, object_scene, observations, states, actions })
}
