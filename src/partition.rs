//! Element-oriented partition: every element belongs to exactly one
//! subdomain (DESIGN.md §2). Recursive coordinate bisection on element
//! midpoints: balanced element counts, compact parts (hence small
//! interfaces), and deterministic (ties broken by element index).

use crate::error::{Error, Result};
use crate::model::Model;

/// Which subdomain each element belongs to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Partition {
    /// Subdomain of each element.
    pub part_of: Vec<usize>,
    /// Elements of each subdomain, in increasing order.
    pub elements_of: Vec<Vec<usize>>,
}

impl Partition {
    /// Number of subdomains.
    pub fn len(&self) -> usize {
        self.elements_of.len()
    }

    /// True when there is no subdomain (never for a built partition).
    pub fn is_empty(&self) -> bool {
        self.elements_of.is_empty()
    }

    fn from_part_of(part_of: Vec<usize>, n_parts: usize) -> Partition {
        let mut elements_of = vec![Vec::new(); n_parts];
        for (e, &p) in part_of.iter().enumerate() {
            elements_of[p].push(e);
        }
        Partition { part_of, elements_of }
    }

    /// Recursive coordinate bisection into `n_parts` subdomains.
    pub fn bisection(model: &Model, n_parts: usize) -> Result<Partition> {
        let ne = model.elements.len();
        if n_parts == 0 {
            return Err(Error::input("solver.subdomains", None, "must be at least 1"));
        }
        if n_parts > ne {
            return Err(Error::input(
                "solver.subdomains",
                None,
                format!("{n_parts} subdomains asked for but the scene has only {ne} elements"),
            ));
        }
        let mid: Vec<[f64; 3]> = model
            .elements
            .iter()
            .map(|el| std::array::from_fn(|d| 0.5 * (model.coords[el.a][d] + model.coords[el.b][d])))
            .collect();
        let mut part_of = vec![0usize; ne];
        let mut ids: Vec<usize> = (0..ne).collect();
        bisect(&mid, &mut ids, 0, n_parts, &mut part_of);
        Ok(Partition::from_part_of(part_of, n_parts))
    }

    /// The user's partition from `elements.subdomain`. Ids must cover
    /// `0..N` with no empty subdomain.
    pub fn from_user(model: &Model, subdomain: &[usize]) -> Result<Partition> {
        let ne = model.elements.len();
        if subdomain.len() != ne {
            return Err(Error::input(
                "elements.subdomain",
                None,
                format!("has {} entries but the scene has {ne} elements", subdomain.len()),
            ));
        }
        // A subdomain needs at least one element, so ids are below the
        // element count (this also bounds the arrays sized from them).
        if let Some(i) = subdomain.iter().position(|&s| s >= ne) {
            return Err(Error::input(
                "elements.subdomain",
                Some(i),
                format!(
                    "subdomain id {} is not below the number of elements ({ne})",
                    subdomain[i]
                ),
            ));
        }
        let n_parts = subdomain.iter().max().map_or(0, |m| m + 1);
        let mut count = vec![0usize; n_parts];
        for &s in subdomain {
            count[s] += 1;
        }
        if let Some(empty) = count.iter().position(|&c| c == 0) {
            return Err(Error::input(
                "elements.subdomain",
                None,
                format!("subdomain ids must cover 0..{n_parts} but subdomain {empty} has no element"),
            ));
        }
        Ok(Partition::from_part_of(subdomain.to_vec(), n_parts))
    }
}

/// Splits `ids` into `parts` parts numbered from `first`, along the axis of
/// largest extent, at the element count proportional to the part counts.
fn bisect(mid: &[[f64; 3]], ids: &mut [usize], first: usize, parts: usize, part_of: &mut [usize]) {
    if parts == 1 {
        for &e in ids.iter() {
            part_of[e] = first;
        }
        return;
    }
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for &e in ids.iter() {
        for d in 0..3 {
            lo[d] = lo[d].min(mid[e][d]);
            hi[d] = hi[d].max(mid[e][d]);
        }
    }
    let axis = (0..3).fold(0, |best, d| if hi[d] - lo[d] > hi[best] - lo[best] { d } else { best });
    let left_parts = parts / 2;
    let split = ids.len() * left_parts / parts;
    // Strict total order (coordinate, then index): deterministic.
    ids.select_nth_unstable_by(split, |&p, &q| mid[p][axis].total_cmp(&mid[q][axis]).then(p.cmp(&q)));
    let (left, right) = ids.split_at_mut(split);
    bisect(mid, left, first, left_parts, part_of);
    bisect(mid, right, first + left_parts, parts - left_parts, part_of);
}
