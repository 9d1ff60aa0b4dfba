//! Subdomains indefinite on their own, merged into neighbours.
//!
//! With geometric stiffness, a compressed strut has negative transverse
//! stiffness. A subdomain that holds struts without the cables that
//! stabilise them is indefinite although the whole structure is not, and
//! its factorization fails. The partition's weak-node repair
//! (`crate::partition`) keeps each strut's end with enough of its cables
//! node by node; what it cannot see is left to this module: on nsdd's own
//! partition the set-up merges such a subdomain into a neighbour
//! ([`Decomposition::merge_target`]) and tries again
//! ([`merges_indefinite`] says when). One failure names one subdomain; in
//! a process that holds every subdomain a pass then factors the others too
//! and merges every indefinite one at once, then only the subdomains the
//! merges made, and so on (as [`merge_indefinite_subdomains`] does from
//! scratch): a tensegrity grid cut in 64 whose cuts leave most subdomains
//! indefinite no longer pays a whole set-up (interiors, deluxe blocks,
//! coarse problem) per merge. Under MPI each rank holds its block of
//! subdomains only, and the merges go one agreed error at a time.

use crate::decomposition::{Decomposition, Merge};
use crate::error::Error;
use crate::model::Model;
use crate::scene::Scene;
use crate::settings::OrderingChoice;
use crate::subdomain::SubdomainOperator;
use rayon::prelude::*;
use std::collections::HashSet;

/// Whether a set-up of `model` on `scene`'s partition merges a subdomain
/// that turns out indefinite into a neighbour and tries again: when the
/// structure has compressed struts (geometric stiffness, which makes a
/// subdomain indefinite where the whole structure is not) and the
/// partition is nsdd's own. A partition given in `elements.subdomain` is
/// the user's to change.
pub fn merges_indefinite(model: &Model, scene: &Scene) -> bool {
    scene.elements.subdomain.is_empty() && model.has_struts()
}

/// The decomposition to try after the set-up error `e` on `dec`, if
/// `merging` and `e` names an indefinite subdomain that has a neighbour,
/// and the merge leaves a subdomain for each of the `ranks` processes:
/// that subdomain merged ([`Decomposition::merge`]). Under MPI every rank
/// gets the same error, so all merge alike.
pub(crate) fn merged_for(
    merging: bool,
    model: &Model,
    dec: &Decomposition,
    e: &Error,
    ranks: usize,
) -> Option<Decomposition> {
    match e {
        Error::IndefiniteSubdomain { subdomain, message } if merging && dec.len() > ranks => {
            dec.merge(model, *subdomain, node_named(message))
        }
        _ => None,
    }
}

/// [`merged_for`] in a process that holds every subdomain, followed by
/// passes as [`merge_indefinite_subdomains`] makes them, over the structure
/// the set-up failed on: `failed`, whose decomposition numbers its
/// subdomains as `dec` does (a nonsmooth step's restricted partition), or
/// `base` and `dec` themselves. The merges are made on `dec`.
pub(crate) fn merged_all_for(
    merging: bool,
    base: &Model,
    dec: &Decomposition,
    e: &Error,
    failed: Option<(&Model, &Decomposition)>,
    ordering: OrderingChoice,
) -> Option<Decomposition> {
    let Error::IndefiniteSubdomain { subdomain, message } = e else {
        return None;
    };
    if !merging {
        return None;
    }
    let (model, on) = failed.unwrap_or((base, dec));
    if on.len() != dec.len() {
        return merged_for(merging, base, dec, e, 1);
    }
    let Some(into) = on.merge_target(model, *subdomain, node_named(message)) else {
        return merged_for(merging, base, dec, e, 1);
    };
    let first = Merge {
        subdomain: *subdomain,
        into,
    };
    // The passes run on the failed structure; their merges are made on
    // `dec`, numbered alike.
    let merges = passes(model, on, vec![first], ordering);
    Some(dec.merge_all(base, &merges))
}

/// `dec` with every subdomain that is indefinite on its own (and has a
/// neighbour) merged into a neighbour, by passes: each factors the
/// subdomains not yet known to factor and merges every indefinite one at
/// once ([`Decomposition::merge_all`], the neighbour from
/// [`Decomposition::merge_target`] at the node its factorization names),
/// until none is left. A clone of `dec` when none is indefinite. What a
/// solve on nsdd's own partition does when it meets such a subdomain
/// (`nsdd partition` reports the count it ends with); for a decomposition
/// of one's own before [`crate::dd::DdSolver::new`].
///
/// ```
/// use nsdd::decomposition::Decomposition;
/// use nsdd::generate::{tensegrity, TensegrityParams};
/// use nsdd::merging::merge_indefinite_subdomains;
/// use nsdd::model::Model;
/// use nsdd::partition::Partition;
/// use nsdd::subdomain::SubdomainOperator;
///
/// let scene = tensegrity(&TensegrityParams { nx: 3, ny: 3, ..Default::default() });
/// let model = Model::from_scene(&scene).unwrap();
/// let dec = Decomposition::new(&model, Partition::bisection(&model, 8).unwrap());
/// let merged = merge_indefinite_subdomains(&model, &dec, Default::default());
/// assert!(merged.len() < 8);
/// for (s, sd) in merged.subdomains.iter().enumerate() {
///     assert!(SubdomainOperator::new(s, &model, sd, 1, Default::default()).is_ok());
/// }
/// ```
pub fn merge_indefinite_subdomains(model: &Model, dec: &Decomposition, ordering: OrderingChoice) -> Decomposition {
    let merges = passes(model, dec, Vec::new(), ordering);
    match merges.is_empty() {
        true => dec.clone(),
        false => dec.merge_all(model, &merges),
    }
}

/// The merges (ids of `on`) of passes over `on` with `first` made first.
fn passes(model: &Model, on: &Decomposition, first: Vec<Merge>, ordering: OrderingChoice) -> Vec<Merge> {
    let mut merged = match first.is_empty() {
        true => on.clone(),
        false => on.merge_all(model, &first),
    };
    let mut merges = first;
    let mut fine = HashSet::new();
    loop {
        let more = indefinite_pass(model, &merged, ordering, &mut fine);
        if more.is_empty() {
            return merges;
        }
        // Ids of `merged` → ids of `on`: each merged subdomain's lowest
        // original id (the numbering of `merge_all`).
        let lowest = lowest_ids(on, &merged);
        merges.extend(more.iter().map(|m| Merge {
            subdomain: lowest[m.subdomain],
            into: lowest[m.into],
        }));
        merged = merged.merge_all(model, &more);
    }
}

/// The error `e` of a set-up on `dec` that merging could not get past
/// (`merging` on, no merge left to make), saying so where `dec` came from
/// merges: down to one subdomain, the structure itself is indefinite (as
/// `direct` would say); above one, the subdomain has no neighbour left or
/// every MPI rank holds one subdomain.
pub(crate) fn past_merging(merging: bool, dec: &Decomposition, e: Error) -> Error {
    match e {
        Error::IndefiniteSubdomain { subdomain, message } if merging && !dec.merged.is_empty() => {
            let asked = dec.len() + dec.merged.len();
            let to = match dec.len() {
                1 => "one, the whole structure, which is not positive definite itself".to_string(),
                n => format!("{n}, which no further merge reduces (no neighbour left, or one per MPI rank)"),
            };
            Error::IndefiniteSubdomain {
                subdomain,
                message: format!(
                    "{message}; the set-up merged the subdomains indefinite on their own from {asked} down to {to}"
                ),
            }
        }
        e => e,
    }
}

/// For each subdomain of `merged` (made from `on` by merges), the lowest
/// id in `on` of the subdomains it joins.
fn lowest_ids(on: &Decomposition, merged: &Decomposition) -> Vec<usize> {
    let mut lowest = vec![usize::MAX; merged.len()];
    for (e, &p) in merged.partition.part_of.iter().enumerate() {
        lowest[p] = lowest[p].min(on.partition.part_of[e]);
    }
    lowest
}

/// Factors every subdomain of `dec` whose elements are not in `fine` and
/// returns a merge for each one that is indefinite on its own and has a
/// neighbour; the element sets that factored join `fine`.
fn indefinite_pass(
    model: &Model,
    dec: &Decomposition,
    ordering: OrderingChoice,
    fine: &mut HashSet<Vec<usize>>,
) -> Vec<Merge> {
    // Per subdomain factored: `Some(near)` when indefinite (the node its
    // factorization names), `None` when it factored. Other failures are
    // the set-up's to report: neither merged nor known to be fine.
    let outcomes: Vec<(usize, Option<Option<usize>>)> = dec
        .subdomains
        .par_iter()
        .enumerate()
        .filter(|(_, sd)| !fine.contains(&sd.elements))
        .filter_map(|(s, sd)| match SubdomainOperator::new(s, model, sd, 1, ordering) {
            Ok(_) => Some((s, None)),
            Err(Error::IndefiniteSubdomain { message, .. }) => Some((s, Some(node_named(&message)))),
            Err(_) => None,
        })
        .collect();
    let mut merges = Vec::new();
    for (s, outcome) in outcomes {
        match outcome {
            None => {
                fine.insert(dec.subdomains[s].elements.clone());
            }
            Some(near) => {
                if let Some(into) = dec.merge_target(model, s, near) {
                    merges.push(Merge { subdomain: s, into });
                }
            }
        }
    }
    merges
}

/// The node an error message names first ("node 12 component x", as the
/// subdomain set-up names its dofs).
pub(crate) fn node_named(message: &str) -> Option<usize> {
    let at = message.find("node ")? + "node ".len();
    let digits: String = message[at..].chars().take_while(|c| c.is_ascii_digit()).collect();
    digits.parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The merge is steered by the node a subdomain's factorization names:
    /// the message of a real indefinite subdomain parses to a node of it.
    #[test]
    fn an_indefinite_subdomain_names_a_node_of_its_own() {
        use crate::dd::{DdOptions, DdSolver};
        use crate::generate::{tensegrity, TensegrityParams};
        use crate::partition::Partition;
        use crate::scene::Method;
        use crate::solve::SolveOptions;
        let scene = tensegrity(&TensegrityParams {
            nx: 3,
            ny: 3,
            unilateral: false,
            ..Default::default()
        });
        let model = Model::from_scene(&scene).unwrap();
        let dec = Decomposition::new(&model, Partition::bisection(&model, 4).unwrap());
        let opts = SolveOptions {
            method: Method::Cg,
            ..Default::default()
        };
        match DdSolver::new(&model, &dec, DdOptions::from_settings(&opts).unwrap()) {
            Err(e @ Error::IndefiniteSubdomain { .. }) => {
                let Error::IndefiniteSubdomain { subdomain, message } = &e else {
                    unreachable!()
                };
                let node = node_named(message).unwrap_or_else(|| panic!("{message}"));
                let own = dec.partition.elements_of[*subdomain]
                    .iter()
                    .any(|&el| model.elements[el].a == node || model.elements[el].b == node);
                assert!(own, "node {node} of {message}");
                let merged = merged_for(true, &model, &dec, &e, 1).expect("a neighbour");
                assert_eq!(merged.len(), 3);
                assert!(merged_for(false, &model, &dec, &e, 1).is_none());
                assert!(
                    merged_for(true, &model, &dec, &e, 4).is_none(),
                    "one subdomain per rank"
                );
            }
            other => panic!("expected an indefinite subdomain: {:?}", other.err()),
        }
        assert_eq!(node_named("at node 17 component y"), Some(17));
        assert_eq!(node_named("no node here"), None);
    }

    /// One failure names one subdomain; the pass finds and merges every
    /// other indefinite one as well, so that every subdomain of the result
    /// factors (the tensegrity grid cut in 16: several are indefinite).
    #[test]
    fn one_pass_merges_every_indefinite_subdomain() {
        use crate::generate::{tensegrity, TensegrityParams};
        use crate::partition::Partition;
        let scene = tensegrity(&TensegrityParams {
            nx: 10,
            ny: 10,
            unilateral: false,
            ..Default::default()
        });
        let model = Model::from_scene(&scene).unwrap();
        let dec = Decomposition::new(&model, Partition::bisection(&model, 16).unwrap());
        let auto = OrderingChoice::Auto;
        let indefinite = |d: &Decomposition| -> Vec<usize> {
            (0..d.len())
                .filter(|&s| {
                    matches!(
                        SubdomainOperator::new(s, &model, &d.subdomains[s], 1, auto),
                        Err(Error::IndefiniteSubdomain { .. })
                    )
                })
                .collect()
        };
        let before = indefinite(&dec);
        assert!(before.len() >= 2, "{before:?}");
        let e = SubdomainOperator::new(before[0], &model, &dec.subdomains[before[0]], 1, auto).unwrap_err();
        let merged = merged_all_for(true, &model, &dec, &e, None, auto).expect("merged");
        assert!(
            merged.len() < 16 - 1,
            "more than the named one merged: {}",
            merged.len()
        );
        assert!(indefinite(&merged).is_empty() || merged.len() == 1);
        assert_eq!(merged.merged.len(), 16 - merged.len());
        // Off: nothing.
        assert!(merged_all_for(false, &model, &dec, &e, None, auto).is_none());
    }
}
