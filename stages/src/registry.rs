//! The registry: the stage kinds and operators one binary knows, by id.

use crate::kind::{Catalog, StageKind};
use crate::operator::DynOperator;

/// The stage kinds and operators an rlmflow binary knows. Each operator has an id, the name
/// keys and plans hold: its name, or `NAME@KIND` for one of an operator serving several kinds
/// (a `script`), each kind's its own definition.
#[derive(Default)]
pub struct Registry {
    pub catalog: Catalog,
    operators: Vec<(String, Box<dyn DynOperator>)>,
    libraries: Vec<&'static str>,
    kernel_pin: Option<fn() -> anyhow::Result<()>>,
}

impl Registry {
    pub fn new(catalog: Catalog) -> Self {
        Registry { catalog, ..Registry::default() }
    }

    /// What makes this binary's numeric library compute as the kernel pins (environment
    /// variables, [`crate::numerics::apply`]) ask, where reading the variables is not enough
    /// (`rlmflow-torch` installs its chain GEMM): run once by `exec`, after the pins are set and
    /// before the operator computes anything.
    pub fn set_kernel_pin(&mut self, pin: fn() -> anyhow::Result<()>) -> &mut Self {
        self.kernel_pin = Some(pin);
        self
    }

    /// Applies the kernel pin, where the binary has one.
    pub fn pin_kernels(&self) -> anyhow::Result<()> {
        self.kernel_pin.map_or(Ok(()), |pin| pin())
    }

    /// Names a numeric library this binary's operators compute with (`libtorch 2.11.0`), for
    /// the provenance of the actions whose bytes depend on it.
    pub fn add_library(&mut self, name: &'static str) -> &mut Self {
        self.libraries.push(name);
        self
    }

    pub fn libraries(&self) -> &[&'static str] {
        &self.libraries
    }

    /// Adds an operator. Panics if its kind is unknown or its name taken: both are programming
    /// errors in the binary that builds the registry, caught by its first test.
    pub fn add(&mut self, op: impl DynOperator + 'static) -> &mut Self {
        let id = op.spec().name.to_owned();
        self.insert(id, Box::new(op))
    }

    /// Adds one definition of an operator that serves several kinds, as `NAME@KIND`: a stage
    /// names it by its name alone, its kind choosing the definition.
    pub fn add_for_kind(&mut self, op: impl DynOperator + 'static) -> &mut Self {
        let spec = op.spec();
        self.insert(format!("{}@{}", spec.name, spec.kind), Box::new(op))
    }

    fn insert(&mut self, id: String, op: Box<dyn DynOperator>) -> &mut Self {
        let spec = op.spec();
        let kind = self.catalog.get(spec.kind).unwrap_or_else(|| panic!("operator `{}` implements unknown stage kind `{}`", spec.name, spec.kind));
        for slot in spec.inputs.unwrap_or(&[]) {
            assert!(kind.slot(slot).is_some(), "operator `{}` reads unknown slot `{slot}`", spec.name);
        }
        assert!(self.find(spec.kind, spec.name).is_none() && self.get(&id).is_none(), "operator `{id}` registered twice");
        self.operators.push((id, op));
        self
    }

    /// The operator of id `id` (as plans and keys name it).
    pub fn get(&self, id: &str) -> Option<&dyn DynOperator> {
        self.operators.iter().find(|(i, _)| i == id).map(|(_, o)| o.as_ref())
    }

    /// The id and definition of the operator a stage of `kind` names `name`.
    pub fn find(&self, kind: &str, name: &str) -> Option<(&str, &dyn DynOperator)> {
        self.operators.iter().find(|(_, o)| o.spec().kind == kind && o.spec().name == name).map(|(i, o)| (i.as_str(), o.as_ref()))
    }

    /// The first operator named `name`, of whichever kind (for a message when a stage names an
    /// operator of another kind).
    pub fn named(&self, name: &str) -> Option<&dyn DynOperator> {
        self.operators.iter().find(|(_, o)| o.spec().name == name).map(|(_, o)| o.as_ref())
    }

    pub fn kind(&self, name: &str) -> Option<&StageKind> {
        self.catalog.get(name)
    }

    /// Operators implementing a stage kind, in registration order.
    pub fn operators_of(&self, kind: &str) -> impl Iterator<Item = &dyn DynOperator> {
        self.operators.iter().filter(move |(_, o)| o.spec().kind == kind).map(|(_, o)| o.as_ref())
    }

    /// Every operator with its id, in registration order.
    pub fn operators(&self) -> impl Iterator<Item = (&str, &dyn DynOperator)> {
        self.operators.iter().map(|(i, o)| (i.as_str(), o.as_ref()))
    }
}
