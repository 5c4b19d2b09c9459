/* A first-order lag as an FMI 2.0 model-exchange FMU, compiled by the tests (tests/fmus).
 *
 * tau·dx/dt = K·(u − u0) − x,  y = y0 + x; initialised at rest with its input (x = K·(u − u0)).
 * With fail_at > 0, its derivatives fail from t > fail_at on, saying why through the logger:
 * the failure an importer must report in the FMU's own words.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "fmi2Functions.h"

enum { K, TAU, U0, Y0, FAIL_AT, U, X, DER_X, Y, N_VARS };

typedef struct {
    fmi2Real r[N_VARS];
    fmi2Real time;
    fmi2CallbackFunctions cb;
    char* name;
} Model;

static void update(Model* m) {
    m->r[DER_X] = (m->r[K] * (m->r[U] - m->r[U0]) - m->r[X]) / m->r[TAU];
    m->r[Y] = m->r[Y0] + m->r[X];
}

static int failing(Model* m) {
    if (m->r[FAIL_AT] > 0 && m->time > m->r[FAIL_AT]) {
        m->cb.logger(m->cb.componentEnvironment, m->name, fmi2Error, "logStatusError",
                     "the flow model diverged at t = %g s", m->time);
        return 1;
    }
    return 0;
}

const char* fmi2GetTypesPlatform(void) { return fmi2TypesPlatform; }
const char* fmi2GetVersion(void) { return fmi2Version; }

fmi2Status fmi2SetDebugLogging(fmi2Component c, fmi2Boolean on, size_t n,
                               const fmi2String categories[]) {
    return fmi2OK;
}

fmi2Component fmi2Instantiate(fmi2String name, fmi2Type type, fmi2String guid,
                              fmi2String resources, const fmi2CallbackFunctions* cb,
                              fmi2Boolean visible, fmi2Boolean loggingOn) {
    if (type != fmi2ModelExchange) return NULL;
    Model* m = calloc(1, sizeof(Model));
    if (!m) return NULL;
    m->cb = *cb;
    m->name = strdup(name ? name : "");
    m->r[K] = 2.0;
    m->r[TAU] = 10.0;
    m->r[U0] = 50.0;
    m->r[Y0] = 50.0;
    m->r[U] = 50.0;
    update(m);
    return m;
}

void fmi2FreeInstance(fmi2Component c) {
    if (c) free(((Model*)c)->name);
    free(c);
}

fmi2Status fmi2SetupExperiment(fmi2Component c, fmi2Boolean tolDef, fmi2Real tol,
                               fmi2Real start, fmi2Boolean stopDef, fmi2Real stop) {
    ((Model*)c)->time = start;
    return fmi2OK;
}

fmi2Status fmi2EnterInitializationMode(fmi2Component c) { return fmi2OK; }

fmi2Status fmi2ExitInitializationMode(fmi2Component c) {
    Model* m = c;
    m->r[X] = m->r[K] * (m->r[U] - m->r[U0]);
    update(m);
    return fmi2OK;
}

fmi2Status fmi2Terminate(fmi2Component c) { return fmi2OK; }
fmi2Status fmi2Reset(fmi2Component c) { return fmi2Error; }

fmi2Status fmi2GetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                       fmi2Real value[]) {
    Model* m = c;
    update(m);
    for (size_t i = 0; i < n; i++) {
        if (vr[i] >= N_VARS) return fmi2Error;
        value[i] = m->r[vr[i]];
    }
    return fmi2OK;
}

fmi2Status fmi2SetReal(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                       const fmi2Real value[]) {
    Model* m = c;
    for (size_t i = 0; i < n; i++) {
        if (vr[i] >= N_VARS || vr[i] == DER_X || vr[i] == Y) return fmi2Error;
        m->r[vr[i]] = value[i];
    }
    update(m);
    return fmi2OK;
}

fmi2Status fmi2GetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                          fmi2Integer v[]) { return fmi2Error; }
fmi2Status fmi2GetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                          fmi2Boolean v[]) { return fmi2Error; }
fmi2Status fmi2GetString(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                         fmi2String v[]) { return fmi2Error; }
fmi2Status fmi2SetInteger(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                          const fmi2Integer v[]) { return fmi2Error; }
fmi2Status fmi2SetBoolean(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                          const fmi2Boolean v[]) { return fmi2Error; }
fmi2Status fmi2SetString(fmi2Component c, const fmi2ValueReference vr[], size_t n,
                         const fmi2String v[]) { return fmi2Error; }
fmi2Status fmi2GetFMUstate(fmi2Component c, fmi2FMUstate* s) { return fmi2Error; }
fmi2Status fmi2SetFMUstate(fmi2Component c, fmi2FMUstate s) { return fmi2Error; }
fmi2Status fmi2FreeFMUstate(fmi2Component c, fmi2FMUstate* s) { return fmi2Error; }
fmi2Status fmi2SerializedFMUstateSize(fmi2Component c, fmi2FMUstate s, size_t* size) {
    return fmi2Error;
}
fmi2Status fmi2SerializeFMUstate(fmi2Component c, fmi2FMUstate s, fmi2Byte b[], size_t n) {
    return fmi2Error;
}
fmi2Status fmi2DeSerializeFMUstate(fmi2Component c, const fmi2Byte b[], size_t n,
                                   fmi2FMUstate* s) { return fmi2Error; }
fmi2Status fmi2GetDirectionalDerivative(fmi2Component c, const fmi2ValueReference u[],
                                        size_t nu, const fmi2ValueReference k[], size_t nk,
                                        const fmi2Real dk[], fmi2Real du[]) {
    return fmi2Error;
}

fmi2Status fmi2EnterEventMode(fmi2Component c) { return fmi2OK; }

fmi2Status fmi2NewDiscreteStates(fmi2Component c, fmi2EventInfo* info) {
    memset(info, 0, sizeof(*info));
    return fmi2OK;
}

fmi2Status fmi2EnterContinuousTimeMode(fmi2Component c) { return fmi2OK; }

fmi2Status fmi2CompletedIntegratorStep(fmi2Component c, fmi2Boolean noSetPrior,
                                       fmi2Boolean* enterEventMode,
                                       fmi2Boolean* terminateSimulation) {
    *enterEventMode = fmi2False;
    *terminateSimulation = fmi2False;
    return fmi2OK;
}

fmi2Status fmi2SetTime(fmi2Component c, fmi2Real time) {
    ((Model*)c)->time = time;
    return fmi2OK;
}

fmi2Status fmi2SetContinuousStates(fmi2Component c, const fmi2Real x[], size_t nx) {
    Model* m = c;
    m->r[X] = x[0];
    update(m);
    return fmi2OK;
}

fmi2Status fmi2GetDerivatives(fmi2Component c, fmi2Real dx[], size_t nx) {
    Model* m = c;
    if (failing(m)) return fmi2Error;
    update(m);
    dx[0] = m->r[DER_X];
    return fmi2OK;
}

fmi2Status fmi2GetEventIndicators(fmi2Component c, fmi2Real z[], size_t nz) { return fmi2OK; }

fmi2Status fmi2GetContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    x[0] = ((Model*)c)->r[X];
    return fmi2OK;
}

fmi2Status fmi2GetNominalsOfContinuousStates(fmi2Component c, fmi2Real x[], size_t nx) {
    x[0] = 1.0;
    return fmi2OK;
}
