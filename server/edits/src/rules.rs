//! What a world accepts in an edit: the species it has, the parameter slots each declares, how large a value may
//! be. The edit writer checks requests with these rules, and every edit read back from a store is checked with the
//! same rules ([`crate::Overlay::from_log_checked`]): a store may hold what the world as loaded cannot take (a
//! species removed from the manifest since, a damaged row), and such an edit is skipped, never served.

use canopy_protocol::ParamRole;

/// Largest magnitude of a parameter value an edit may set (species declare no ranges; this keeps values sane).
pub const MAX_PARAM_VALUE: f32 = 1.0e4;

/// The world's rules for edits (see the module docs).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EditRules {
    /// The slots an edit may set (the species' parameters, not its working values), by species id; the table's
    /// length is the species count.
    params: Vec<Vec<u16>>,
}

impl EditRules {
    /// Rules for a world whose species `i` has the parameter slots `params[i]`.
    pub fn new(params: Vec<Vec<u16>>) -> EditRules {
        EditRules { params }
    }

    /// Rules for a world of these species, in table order.
    pub fn of_species<'a>(graphs: impl IntoIterator<Item = &'a canopy_protocol::SpeciesGraph>) -> EditRules {
        let slots = |g: &'a canopy_protocol::SpeciesGraph| g.of_role(ParamRole::Parameter).map(|(s, _)| s).collect();
        EditRules::new(graphs.into_iter().map(slots).collect())
    }

    /// How many species the world has.
    pub fn species(&self) -> usize {
        self.params.len()
    }

    /// Whether the world has species `species`.
    pub fn check_species(&self, species: u8) -> Result<(), String> {
        if usize::from(species) < self.params.len() {
            Ok(())
        } else {
            Err(format!("species {species} is not in the world's table"))
        }
    }

    /// Whether `params` (`(slot, value)`) fit species `species`: its parameters' slots (never a working value's),
    /// values within ±[`MAX_PARAM_VALUE`].
    pub fn check_params(&self, species: u8, params: &[(u16, f32)]) -> Result<(), String> {
        let declared = self.params.get(usize::from(species)).map_or(&[][..], Vec::as_slice);
        if let Some((slot, _)) = params.iter().find(|(s, _)| !declared.contains(s)) {
            return Err(format!("species {species} declares no parameter slot {slot}"));
        }
        if let Some((slot, v)) = params.iter().find(|(_, v)| v.is_nan() || v.abs() > MAX_PARAM_VALUE) {
            return Err(format!("parameter {slot} = {v} is beyond ±{MAX_PARAM_VALUE}"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn species_slots_and_values_are_checked() {
        let r = EditRules::new(vec![vec![0, 1], vec![]]);
        assert_eq!(r.species(), 2);
        assert!(r.check_species(1).is_ok());
        assert!(r.check_species(2).unwrap_err().contains("species 2"));
        assert!(r.check_params(0, &[(0, 1.0), (1, -MAX_PARAM_VALUE)]).is_ok());
        assert!(r.check_params(0, &[(2, 1.0)]).unwrap_err().contains("slot 2"));
        assert!(r.check_params(1, &[(0, 1.0)]).is_err());
        assert!(r.check_params(0, &[(1, 1.0e30)]).unwrap_err().contains("beyond"));
        assert!(r.check_params(0, &[(1, f32::NAN)]).is_err());
        assert!(r.check_params(9, &[]).is_ok());
    }

    #[test]
    fn a_working_value_is_not_for_an_edit_to_set() {
        use canopy_protocol::{Expr, Node, ParamDecl, ParamRole, ParamScope, SpeciesGraph};
        let decl = |name: &str, role| ParamDecl {
            name: name.into(),
            default: Expr::constant(1.0),
            scope: ParamScope::Local,
            role,
        };
        let params = vec![decl("height", ParamRole::Parameter), decl("n", ParamRole::Working)];
        let g = SpeciesGraph { name: "t".into(), params, nodes: vec![Node::Group(vec![])], root: 0 };
        let r = EditRules::of_species([&g]);
        assert!(r.check_params(0, &[(0, 2.0)]).is_ok());
        assert!(r.check_params(0, &[(1, 2.0)]).unwrap_err().contains("slot 1"));
    }
}
