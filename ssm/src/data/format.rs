//! Reading and writing dataset directories (SPEC §4).
//!
//! The CSV files hold only integers and numbers, so a small strict reader is
//! used instead of a general CSV parser: comma-separated fields, surrounding
//! spaces trimmed, blank lines skipped, no quoting. Line 1 must be the exact
//! header. Numbers are written in Rust's shortest round-trip form, so
//! write -> read is bit-exact.

use super::builder::{assemble, Rec, Records};
use super::error::{DataError, Place, Problem};
use super::meta::{parse_meta, render_meta};
use super::{
    Action, BoxDetection, Dataset, Object, ObservationKind, Observations, Pose, Prior, State, ACTIONS_FILE,
    ACTION_COLUMNS, AV_COLUMNS, AV_FILE, BOXES_FILE, BOX_COLUMNS, META_FILE, OBJECTS_FILE, OBJECT_COLUMNS, POINTS_FILE,
    POINT_COLUMNS, STATES_FILE, STATE_COLUMNS,
};
use std::fs;
use std::io::{self, BufWriter, Write};
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

/// The most columns any dataset file has.
const MAX_COLUMNS: usize = 14;

/// Reads a whole text file; a missing file is [`DataError::MissingFile`].
fn read_text(path: &Path) -> Result<String, DataError> {
    fs::read_to_string(path).map_err(|e| {
        if e.kind() == io::ErrorKind::NotFound {
            DataError::MissingFile { path: path.to_path_buf() }
        } else {
            DataError::io(path, e)
        }
    })
}

/// One data row of a CSV file, with typed accessors that report bad fields.
pub(crate) struct Row<'a> {
    file: &'a str,
    line: usize,
    columns: &'a [&'a str],
    fields: [&'a str; MAX_COLUMNS],
}

impl Row<'_> {
    fn place(&self) -> Place {
        Place::Line(self.line)
    }

    fn malformed(&self, i: usize, expected: &'static str) -> DataError {
        DataError::invalid(
            self.file,
            self.place(),
            self.columns[i],
            Problem::Malformed { text: self.fields[i].to_string(), expected },
        )
    }

    /// Field `i` as an integer.
    fn int(&self, i: usize) -> Result<i64, DataError> {
        self.fields[i].parse::<i64>().map_err(|_| self.malformed(i, "an integer"))
    }

    /// Field `i` as a finite number.
    fn num(&self, i: usize) -> Result<f64, DataError> {
        let text = self.fields[i];
        let v: f64 = text.parse().map_err(|_| self.malformed(i, "a number"))?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err(DataError::invalid(
                self.file,
                self.place(),
                self.columns[i],
                Problem::NonFinite { text: text.to_string() },
            ))
        }
    }
}

/// Reads the CSV file `name` of `dir`: checks the header and the field count
/// of every row, and turns each row into a `T` with `parse`.
fn read_csv<T>(
    dir: &Path,
    name: &'static str,
    columns: &'static [&'static str],
    mut parse: impl FnMut(&Row<'_>) -> Result<T, DataError>,
) -> Result<Vec<T>, DataError> {
    let text = read_text(&dir.join(name))?;
    let text = text.strip_prefix('\u{feff}').unwrap_or(&text);
    let mut lines = text.split('\n').map(|l| l.strip_suffix('\r').unwrap_or(l));
    let header: Vec<&str> = lines.next().unwrap_or("").split(',').map(str::trim).collect();
    if header != columns {
        let i = header.iter().zip(columns).position(|(a, b)| a != b).unwrap_or(header.len().min(columns.len()));
        let column = columns.get(i).or(header.get(i)).copied().unwrap_or("-");
        return Err(DataError::invalid(
            name,
            Place::Line(1),
            column,
            Problem::Header { expected: columns.join(","), found: header.join(",") },
        ));
    }
    let mut out = Vec::new();
    for (k, line) in lines.enumerate() {
        let line_no = k + 2;
        if line.trim().is_empty() {
            continue;
        }
        let mut row = Row { file: name, line: line_no, columns, fields: [""; MAX_COLUMNS] };
        let mut count = 0;
        for f in line.split(',') {
            if count < MAX_COLUMNS {
                row.fields[count] = f.trim();
            }
            count += 1;
        }
        if count != columns.len() {
            let column = if count < columns.len() {
                columns[count].to_string()
            } else {
                format!("(extra field {})", columns.len() + 1)
            };
            return Err(DataError::invalid(
                name,
                Place::Line(line_no),
                column,
                Problem::FieldCount { expected: columns.len(), found: count },
            ));
        }
        out.push(parse(&row)?);
    }
    Ok(out)
}

/// Reads and validates the dataset in `dir`.
pub(crate) fn read_dir(dir: &Path) -> Result<Dataset, DataError> {
    let meta = parse_meta(&read_text(&dir.join(META_FILE))?)?;
    let has_points = dir.join(POINTS_FILE).exists();
    let has_boxes = dir.join(BOXES_FILE).exists();
    let kind = match (has_points, has_boxes) {
        (true, false) => ObservationKind::Points,
        (false, true) => ObservationKind::Boxes,
        (both, _) => return Err(DataError::ObservationFiles { dir: dir.to_path_buf(), both }),
    };

    let mut records = Records {
        av: read_csv(dir, AV_FILE, &AV_COLUMNS, |r| {
            // Parse in column order so the first bad column is reported.
            let (scene, t) = (r.int(0)?, r.int(1)?);
            let value = Pose { x: r.num(2)?, y: r.num(3)?, yaw: r.num(4)? };
            Ok(Rec { place: r.place(), scene, object: 0, t, value })
        })?,
        objects: read_csv(dir, OBJECTS_FILE, &OBJECT_COLUMNS, |r| {
            let (scene, id) = (r.int(0)?, r.int(1)?);
            let (length, width) = (r.num(2)?, r.num(3)?);
            let mut v = [0.0; 10];
            for (i, x) in v.iter_mut().enumerate() {
                *x = r.num(4 + i)?;
            }
            let mean = State::from_array([v[0], v[1], v[2], v[3], v[4]]);
            let sd = State::from_array([v[5], v[6], v[7], v[8], v[9]]);
            Ok(Rec {
                place: r.place(),
                scene,
                object: id,
                t: 0,
                value: Object { scene, id, length, width, prior: Prior { mean, sd } },
            })
        })?,
        ..Records::default()
    };
    match kind {
        ObservationKind::Points => {
            records.points = read_csv(dir, POINTS_FILE, &POINT_COLUMNS, |r| {
                let key = (r.int(0)?, r.int(1)?, r.int(2)?);
                keyed(r, key, [r.num(3)?, r.num(4)?])
            })?
        }
        ObservationKind::Boxes => {
            records.boxes = read_csv(dir, BOXES_FILE, &BOX_COLUMNS, |r| {
                let key = (r.int(0)?, r.int(1)?, r.int(2)?);
                let value = BoxDetection {
                    x: r.num(3)?,
                    y: r.num(4)?,
                    yaw: r.num(5)?,
                    length: r.num(6)?,
                    width: r.num(7)?,
                    score: r.num(8)?,
                };
                keyed(r, key, value)
            })?
        }
    }
    if dir.join(STATES_FILE).exists() {
        records.states = Some(read_csv(dir, STATES_FILE, &STATE_COLUMNS, |r| {
            let key = (r.int(0)?, r.int(1)?, r.int(2)?);
            let mut v = [0.0; 5];
            for (i, x) in v.iter_mut().enumerate() {
                *x = r.num(3 + i)?;
            }
            keyed(r, key, State::from_array(v))
        })?);
    }
    if dir.join(ACTIONS_FILE).exists() {
        records.actions = Some(read_csv(dir, ACTIONS_FILE, &ACTION_COLUMNS, |r| {
            let key = (r.int(0)?, r.int(1)?, r.int(2)?);
            let value = Action { accel: r.num(3)?, pinch: r.num(4)? };
            keyed(r, key, value)
        })?);
    }
    assemble(meta, kind, records)
}

/// A record keyed by (scene, object, t); the key is parsed before the value
/// so that the first bad column is the one reported.
fn keyed<T>(row: &Row<'_>, key: (i64, i64, i64), value: T) -> Result<Rec<T>, DataError> {
    Ok(Rec { place: row.place(), scene: key.0, object: key.1, t: key.2, value })
}

/// Distinguishes temporary files of concurrent writers in one process.
static TMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Writes `dir/name` atomically: into a temporary file in `dir`, synced, then
/// renamed over the target. On failure the temporary file is removed and the
/// previous `dir/name` (if any) is untouched.
fn write_atomic(
    dir: &Path,
    name: &str,
    body: impl FnOnce(&mut BufWriter<fs::File>) -> io::Result<()>,
) -> Result<(), DataError> {
    let n = TMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    let tmp = dir.join(format!(".{name}.tmp-{}-{n}", std::process::id()));
    let result = (|| -> io::Result<()> {
        let mut w = BufWriter::new(fs::File::create(&tmp)?);
        body(&mut w)?;
        let file = w.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()
    })();
    if let Err(e) = result {
        let _ = fs::remove_file(&tmp);
        return Err(DataError::io(tmp, e));
    }
    let target = dir.join(name);
    fs::rename(&tmp, &target).map_err(|e| {
        let _ = fs::remove_file(&tmp);
        DataError::io(target, e)
    })
}

/// Writes a row of numbers after the integer key fields.
fn row(w: &mut impl Write, key: &[i64], values: &[f64]) -> io::Result<()> {
    for (i, k) in key.iter().enumerate() {
        if i > 0 {
            w.write_all(b",")?;
        }
        write!(w, "{k}")?;
    }
    for v in values {
        // `{:?}` is the shortest representation that parses back to the same bits.
        write!(w, ",{v:?}")?;
    }
    w.write_all(b"\n")
}

fn header(w: &mut impl Write, columns: &[&str]) -> io::Result<()> {
    writeln!(w, "{}", columns.join(","))
}

/// Writes `ds` into `dir`.
pub(crate) fn write_dir(ds: &Dataset, dir: &Path) -> Result<(), DataError> {
    fs::create_dir_all(dir).map_err(|e| DataError::io(dir, e))?;
    let objects = ds.objects();
    let key = |o: usize, t: usize| [objects[o].scene, objects[o].id, t as i64];

    write_atomic(dir, AV_FILE, |w| {
        header(w, &AV_COLUMNS)?;
        for s in ds.scenes() {
            for (t, p) in s.av.iter().enumerate() {
                row(w, &[s.id, t as i64], &[p.x, p.y, p.yaw])?;
            }
        }
        Ok(())
    })?;
    write_atomic(dir, OBJECTS_FILE, |w| {
        header(w, &OBJECT_COLUMNS)?;
        for o in objects {
            let m = o.prior.mean.to_array();
            let s = o.prior.sd.to_array();
            let mut v = vec![o.length, o.width];
            v.extend_from_slice(&m);
            v.extend_from_slice(&s);
            row(w, &[o.scene, o.id], &v)?;
        }
        Ok(())
    })?;
    let stale_obs = match ds.observations() {
        Observations::Points(p) => {
            write_atomic(dir, POINTS_FILE, |w| {
                header(w, &POINT_COLUMNS)?;
                for (o, t, xy) in p.iter() {
                    row(w, &key(o, t), &xy)?;
                }
                Ok(())
            })?;
            BOXES_FILE
        }
        Observations::Boxes(b) => {
            write_atomic(dir, BOXES_FILE, |w| {
                header(w, &BOX_COLUMNS)?;
                for (o, t, d) in b.iter() {
                    row(w, &key(o, t), &[d.x, d.y, d.yaw, d.length, d.width, d.score])?;
                }
                Ok(())
            })?;
            POINTS_FILE
        }
    };
    let mut stale = vec![stale_obs];
    match ds.states() {
        Some(states) => write_atomic(dir, STATES_FILE, |w| {
            header(w, &STATE_COLUMNS)?;
            for (o, t, s) in states.iter() {
                row(w, &key(o, t), &s.to_array())?;
            }
            Ok(())
        })?,
        None => stale.push(STATES_FILE),
    }
    match ds.actions() {
        Some(actions) => write_atomic(dir, ACTIONS_FILE, |w| {
            header(w, &ACTION_COLUMNS)?;
            for (o, t, a) in actions.iter() {
                row(w, &key(o, t), &[a.accel, a.pinch])?;
            }
            Ok(())
        })?,
        None => stale.push(ACTIONS_FILE),
    }
    let meta_text = render_meta(&ds.meta());
    write_atomic(dir, META_FILE, |w| w.write_all(meta_text.as_bytes()))?;
    for name in stale {
        let path = dir.join(name);
        match fs::remove_file(&path) {
            Ok(()) => {}
            Err(e) if e.kind() == io::ErrorKind::NotFound => {}
            Err(e) => return Err(DataError::io(path, e)),
        }
    }
    Ok(())
}
