// Gradient shading of DVR samples on the device, twin of `shading.rs`:
// the gradient by central differences one voxel of the sample's level
// apart along each world axis, each neighbour looked up like a sample
// (through the page tables, so a neighbour in the next brick is read from
// that brick or from its stand-in, and requested when missing; the lookups
// count as samples, so a frame is complete only when they are all served
// at their level); Blinn–Phong with the light at the eye.

// Neighbour lookups of this invocation: samples, exact, unserved.
var<private> nb_samples: u32;
var<private> nb_exact: u32;
var<private> nb_unserved: u32;

fn neighbour(l: u32, w: vec3<f32>) -> vec2<f32> {
    let s = sample_at(w, l);
    nb_samples = nb_samples + 1u;
    nb_exact = nb_exact + u32(s.y == 2.0);
    nb_unserved = nb_unserved + u32(s.y == 0.0);
    return s;
}

// The gradient (world units) of level `l`'s sampled field at world point
// `w`; w = 0 when a neighbour is not served at all.
fn gradient(l: u32, w: vec3<f32>) -> vec4<f32> {
    var g = vec3<f32>(0.0);
    for (var a = 0u; a < 3u; a = a + 1u) {
        // A voxel of level `l` along world axis `a` (volume axis 2 − a).
        let h = 1.0 / R.scale[l][2u - a];
        var p = w;
        p[a] = w[a] + h;
        let hi = neighbour(l, p);
        p[a] = w[a] - h;
        let lo = neighbour(l, p);
        if (hi.y == 0.0 || lo.y == 0.0) {
            return vec4<f32>(0.0);
        }
        g[a] = (hi.x - lo.x) / (2.0 * h);
    }
    return vec4<f32>(g, 1.0);
}

// |ĝ·d̂| (negative for a zero gradient).
fn cosine(g: vec3<f32>, d: vec3<f32>) -> f32 {
    let gg = dot(g, g);
    if (gg == 0.0) {
        return -1.0;
    }
    return abs(dot(g, d) / sqrt(gg * dot(d, d)));
}

// Colour `c` lit at cosine `x`: c·(ambient + diffuse·x) + specular·x^shininess.
fn lit(c: vec3<f32>, x: f32) -> vec3<f32> {
    let sh = R.shading;
    return c * (sh.x + sh.y * x) + vec3<f32>(sh.z * pow(x, sh.w));
}

// Colour `c` of the sample at world point `w` of level `l` on a ray of
// direction `d`, shaded (unshaded while a neighbour is not served, or for
// a zero gradient).
fn shade(c: vec3<f32>, l: u32, w: vec3<f32>, d: vec3<f32>) -> vec3<f32> {
    let g = gradient(l, w);
    if (g.w == 0.0) {
        return c;
    }
    let x = cosine(g.xyz, d);
    if (x < 0.0) {
        return c;
    }
    return lit(c, x);
}
