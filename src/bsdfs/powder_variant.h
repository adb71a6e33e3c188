#pragma once

/*
 * The Mitsuba variant a translation unit of the plugin is compiled for, and its
 * registration. CMake compiles powder.cpp once per variant with POWDER_VARIANT=<name> and
 * that variant's types (POWDER_BACKEND_<scalar|llvm|cuda>, POWDER_CHANNELS = 3 (RGB), 1
 * (mono) or 0 (spectral), POWDER_POLARIZED), so that the variants build in parallel and
 * incrementally; POWDER_EXPORT_VARIANT(Powder) at the end of powder.cpp defines that
 * variant's registration function powder_register_<variant>, which the plugin's entry
 * point (powder_plugin.cpp) calls for every variant built.
 */

#include <mitsuba/core/fwd.h>
#include <mitsuba/core/object.h>
#include <mitsuba/core/properties.h>
#include <mitsuba/core/spectrum.h>

#include <string_view>

#define POWDER_CAT_(a, b) a##b
#define POWDER_CAT(a, b) POWDER_CAT_(a, b)
#define POWDER_STR_(a) #a
#define POWDER_STR(a) POWDER_STR_(a)

#if !defined(POWDER_VARIANT)
#error "compile powder.cpp with POWDER_VARIANT=<variant> (CMakeLists.txt)"
#endif

NAMESPACE_BEGIN(mitsuba)
namespace powder_variant {
#if defined(POWDER_BACKEND_scalar)
    using F = float;
#elif defined(POWDER_BACKEND_llvm)
    using F = dr::DiffArray<JitBackend::LLVM, float>;
#elif defined(POWDER_BACKEND_cuda)
    using F = dr::DiffArray<JitBackend::CUDA, float>;
#else
#error "POWDER_BACKEND_<scalar|llvm|cuda> is not defined"
#endif
#if POWDER_CHANNELS == 0
    using U = Spectrum<F, 4>;
#else
    using U = Color<F, POWDER_CHANNELS>;
#endif
#if POWDER_POLARIZED
    using S = MuellerMatrix<U>;
#else
    using S = U;
#endif
    constexpr bool same(const char *a, const char *b) {
        return *a == *b && (*a == '\0' || same(a + 1, b + 1));
    }
    static_assert(detail::variant<F, S>::name != nullptr &&
                      same(detail::variant<F, S>::name, POWDER_STR(POWDER_VARIANT)),
                  "the types derived from POWDER_VARIANT do not match the installed "
                  "Mitsuba's variant of that name");
} // namespace powder_variant
NAMESPACE_END(mitsuba)

/// The registration of the class template `Name` in the variant of this translation unit
/// (inside namespace mitsuba, like Mitsuba's MI_EXPORT_PLUGIN)
#define POWDER_EXPORT_VARIANT(Name)                                                         \
    void POWDER_CAT(powder_register_, POWDER_VARIANT)(std::string_view name,                \
                                                       PluginRegisterFn fn) {               \
        using P = Name<powder_variant::F, powder_variant::S>;                               \
        fn(name, P::Variant, P::Type,                                                        \
           [](void *, const Properties &p) -> ref<Object> { return new P(p); });            \
    }
