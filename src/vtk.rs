//! VTK output for ParaView: a hand-written XML UnstructuredGrid (`.vtu`,
//! ASCII) writer for one solution, and a `.pvd` collection for a series of
//! them (load steps, load cases).
//!
//! Hand-written because the format needed here is tiny (points, line cells,
//! a few arrays) and the VTK crates are unmaintained (notes/faer-and-crates.md).
//! ASCII rather than binary so the files can be diffed and read back by tests.
//!
//! Layout of a `.vtu`: points are the node coordinates; each element is a
//! `VTK_LINE` cell (type 3) from `a` to `b`; point data `displacement`
//! (3 components, use ParaView's "Warp By Vector" to see the deformed shape);
//! cell data `tension` (Float64), `slack` (Int32 0/1), `subdomain` (Int32, 0
//! when there is no decomposition) and `kind` (Int32: 0 bar, 1 cable).
//! Numbers are written in shortest round-trip exponent form (`1.5e-3`), so
//! reading them back gives the same `f64`.

use std::fmt::Write as _;
use std::io::Write;
use std::path::Path;

use crate::error::{Error, Result};
use crate::model::Model;
use crate::scene::ElementKind;

/// `VTK_LINE` cell type.
pub const VTK_LINE: u8 = 3;

fn check_len(field: &str, len: usize, expected: usize, what: &str) -> Result<()> {
    if len != expected {
        return Err(Error::input(
            field,
            None,
            format!("has {len} entries but the model has {expected} {what}"),
        ));
    }
    Ok(())
}

/// Writes `items` as the body of a `<DataArray>`, a bounded number per line.
fn rows<T>(
    w: &mut impl Write,
    items: impl Iterator<Item = T>,
    per_line: usize,
    mut item: impl FnMut(&mut dyn Write, T) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let mut k = 0;
    for x in items {
        w.write_all(if k == 0 { b"          " } else { b" " })?;
        item(w, x)?;
        k += 1;
        if k == per_line {
            w.write_all(b"\n")?;
            k = 0;
        }
    }
    if k != 0 {
        w.write_all(b"\n")?;
    }
    Ok(())
}

/// Writes a float so that it reads back to the same `f64` (shortest
/// round-trip exponent form); non-finite values as `nan`, `inf`, `-inf`.
fn float(w: &mut dyn Write, v: f64) -> std::io::Result<()> {
    if v.is_finite() {
        write!(w, "{v:e}")
    } else if v.is_nan() {
        w.write_all(b"nan")
    } else if v > 0.0 {
        w.write_all(b"inf")
    } else {
        w.write_all(b"-inf")
    }
}

/// Writes the `.vtu` document to `w`. Arguments as in [`write_vtu`].
pub fn write_vtu_to(
    w: &mut impl Write,
    model: &Model,
    displacements: &[[f64; 3]],
    tensions: &[f64],
    slack: &[bool],
    subdomain: Option<&[usize]>,
) -> Result<()> {
    let n = model.coords.len();
    let m = model.elements.len();
    check_len("displacements", displacements.len(), n, "nodes")?;
    check_len("tensions", tensions.len(), m, "elements")?;
    check_len("slack", slack.len(), m, "elements")?;
    if let Some(s) = subdomain {
        check_len("subdomain", s.len(), m, "elements")?;
        if let Some(i) = s.iter().position(|&v| v > i32::MAX as usize) {
            return Err(Error::input("subdomain", Some(i), "does not fit in an Int32"));
        }
    }
    write_body(w, model, displacements, tensions, slack, subdomain).map_err(|e| Error::Io(e.to_string()))
}

fn write_body(
    w: &mut impl Write,
    model: &Model,
    displacements: &[[f64; 3]],
    tensions: &[f64],
    slack: &[bool],
    subdomain: Option<&[usize]>,
) -> std::io::Result<()> {
    let n = model.coords.len();
    let m = model.elements.len();
    writeln!(w, "<?xml version=\"1.0\"?>")?;
    writeln!(
        w,
        "<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt64\">"
    )?;
    writeln!(w, "  <UnstructuredGrid>")?;
    writeln!(w, "    <Piece NumberOfPoints=\"{n}\" NumberOfCells=\"{m}\">")?;

    writeln!(w, "      <PointData Vectors=\"displacement\">")?;
    writeln!(
        w,
        "        <DataArray type=\"Float64\" Name=\"displacement\" NumberOfComponents=\"3\" format=\"ascii\">"
    )?;
    rows(w, displacements.iter(), 2, |w, d| {
        float(w, d[0])?;
        w.write_all(b" ")?;
        float(w, d[1])?;
        w.write_all(b" ")?;
        float(w, d[2])
    })?;
    writeln!(w, "        </DataArray>")?;
    writeln!(w, "      </PointData>")?;

    writeln!(w, "      <CellData Scalars=\"tension\">")?;
    writeln!(
        w,
        "        <DataArray type=\"Float64\" Name=\"tension\" format=\"ascii\">"
    )?;
    rows(w, tensions.iter(), 6, |w, &t| float(w, t))?;
    writeln!(w, "        </DataArray>")?;
    writeln!(w, "        <DataArray type=\"Int32\" Name=\"slack\" format=\"ascii\">")?;
    rows(w, slack.iter(), 20, |w, &s| w.write_all(if s { b"1" } else { b"0" }))?;
    writeln!(w, "        </DataArray>")?;
    writeln!(
        w,
        "        <DataArray type=\"Int32\" Name=\"subdomain\" format=\"ascii\">"
    )?;
    rows(w, 0..m, 20, |w, e| write!(w, "{}", subdomain.map_or(0, |s| s[e])))?;
    writeln!(w, "        </DataArray>")?;
    writeln!(w, "        <DataArray type=\"Int32\" Name=\"kind\" format=\"ascii\">")?;
    rows(w, model.elements.iter(), 20, |w, el| {
        w.write_all(if el.kind == ElementKind::Cable { b"1" } else { b"0" })
    })?;
    writeln!(w, "        </DataArray>")?;
    writeln!(w, "      </CellData>")?;

    writeln!(w, "      <Points>")?;
    writeln!(
        w,
        "        <DataArray type=\"Float64\" Name=\"Points\" NumberOfComponents=\"3\" format=\"ascii\">"
    )?;
    rows(w, model.coords.iter(), 2, |w, c| {
        float(w, c[0])?;
        w.write_all(b" ")?;
        float(w, c[1])?;
        w.write_all(b" ")?;
        float(w, c[2])
    })?;
    writeln!(w, "        </DataArray>")?;
    writeln!(w, "      </Points>")?;

    writeln!(w, "      <Cells>")?;
    writeln!(
        w,
        "        <DataArray type=\"Int64\" Name=\"connectivity\" format=\"ascii\">"
    )?;
    rows(w, model.elements.iter(), 8, |w, el| write!(w, "{} {}", el.a, el.b))?;
    writeln!(w, "        </DataArray>")?;
    writeln!(
        w,
        "        <DataArray type=\"Int64\" Name=\"offsets\" format=\"ascii\">"
    )?;
    rows(w, 1..=m, 16, |w, e| write!(w, "{}", 2 * e))?;
    writeln!(w, "        </DataArray>")?;
    writeln!(w, "        <DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">")?;
    rows(w, 0..m, 32, |w, _| write!(w, "{VTK_LINE}"))?;
    writeln!(w, "        </DataArray>")?;
    writeln!(w, "      </Cells>")?;

    writeln!(w, "    </Piece>")?;
    writeln!(w, "  </UnstructuredGrid>")?;
    writeln!(w, "</VTKFile>")?;
    Ok(())
}

/// The `.vtu` document as a string (what [`write_vtu`] writes). Errors if an
/// array's length does not match the model (`displacements` per node,
/// `tensions`, `slack` and `subdomain` per element).
pub fn to_vtu_string(
    model: &Model,
    displacements: &[[f64; 3]],
    tensions: &[f64],
    slack: &[bool],
    subdomain: Option<&[usize]>,
) -> Result<String> {
    let mut buf = Vec::new();
    write_vtu_to(&mut buf, model, displacements, tensions, slack, subdomain)?;
    String::from_utf8(buf).map_err(|e| Error::Numerical(format!("vtu output is not UTF-8: {e}")))
}

/// Writes one solution as an XML UnstructuredGrid file (`.vtu`, ASCII):
/// node displacements (per node, zeros on blocked components), element
/// tensions, slack flags and, when given, the subdomain of each element.
/// The file is streamed, so scenes of millions of elements need no
/// in-memory copy of the document.
pub fn write_vtu(
    path: impl AsRef<Path>,
    model: &Model,
    displacements: &[[f64; 3]],
    tensions: &[f64],
    slack: &[bool],
    subdomain: Option<&[usize]>,
) -> Result<()> {
    let path = path.as_ref();
    let io = |e: std::io::Error| Error::Io(format!("{}: {e}", path.display()));
    let file = std::fs::File::create(path).map_err(io)?;
    let mut w = std::io::BufWriter::new(file);
    write_vtu_to(&mut w, model, displacements, tensions, slack, subdomain).map_err(|e| match e {
        Error::Io(m) => Error::Io(format!("{}: {m}", path.display())),
        other => other,
    })?;
    w.flush().map_err(io)
}

/// Escapes the five XML special characters for an attribute value.
fn xml_attr(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&apos;"),
            _ => out.push(c),
        }
    }
    out
}

/// The `.pvd` collection document for `steps` = `(time or load factor,
/// .vtu file name relative to the .pvd)`. A non-finite time is an error
/// naming the step.
pub fn to_pvd_string(steps: &[(f64, String)]) -> Result<String> {
    if let Some(i) = steps.iter().position(|(t, _)| !t.is_finite()) {
        return Err(Error::input("steps", Some(i), "time is not a finite number"));
    }
    let mut s = String::from("<?xml version=\"1.0\"?>\n");
    s.push_str("<VTKFile type=\"Collection\" version=\"0.1\" byte_order=\"LittleEndian\">\n");
    s.push_str("  <Collection>\n");
    for (t, file) in steps {
        // Writing to a String cannot fail.
        let _ = writeln!(
            s,
            "    <DataSet timestep=\"{t:e}\" group=\"\" part=\"0\" file=\"{}\"/>",
            xml_attr(file)
        );
    }
    s.push_str("  </Collection>\n");
    s.push_str("</VTKFile>\n");
    Ok(s)
}

/// Writes a ParaView `.pvd` collection: a time series (load steps or load
/// cases) of `.vtu` files, each with its time or load factor. ParaView opens
/// the `.pvd` and animates the steps.
pub fn write_pvd_series(path: impl AsRef<Path>, steps: &[(f64, String)]) -> Result<()> {
    let path = path.as_ref();
    let text = to_pvd_string(steps)?;
    std::fs::write(path, text).map_err(|e| Error::Io(format!("{}: {e}", path.display())))
}
